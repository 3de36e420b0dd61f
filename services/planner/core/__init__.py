"""Planner core: step context, compressed history, the sub-path prompt and the policy backends.

Pure Python (numpy/opencv/openai SDK); the bus adapter (``services/planner/service.py``) decodes
requests, calls into here and encodes replies. Importing this package registers every backend in
:data:`POLICIES`: ``openai``, ``heuristic``, ``replay``, ``oracle``.
"""

from .context import (
    Ablation,
    CandidateView,
    OracleInfo,
    StepContext,
    build_candidate_views,
    candidate_world_heading,
    nearest_view_index,
    with_stop_and_backtrack,
)
from .errors import AnswerError, ContextError, PlannerError, PolicyBackendError, ReplayMissError
from .heuristic import HeuristicConfig, HeuristicPolicy
from .history import ActionKind, ActionRecord, HistoryItem, HistoryRecorder, action_for, compress
from .instruction import ParsedInstruction, SubGoal, Turn, parse_instruction
from .openai_policy import OpenAIConfig, OpenAIPolicy
from .oracle import OracleConfig, OraclePolicy
from .policy import POLICIES, Policy
from .prompt import Prompt, PromptBuilder, PromptConfig, PromptImage, corrective_message, parse_answer
from .replay import ReplayConfig, ReplayPolicy

__all__ = [
    "POLICIES", "Ablation", "ActionKind", "ActionRecord", "AnswerError", "CandidateView", "ContextError",
    "HeuristicConfig", "HeuristicPolicy", "HistoryItem", "HistoryRecorder", "OpenAIConfig", "OpenAIPolicy",
    "OracleConfig", "OracleInfo", "OraclePolicy", "ParsedInstruction", "PlannerError", "Policy",
    "PolicyBackendError", "Prompt", "PromptBuilder", "PromptConfig", "PromptImage", "ReplayConfig",
    "ReplayMissError", "ReplayPolicy", "StepContext", "SubGoal", "Turn", "action_for",
    "build_candidate_views", "candidate_world_heading", "compress", "corrective_message",
    "nearest_view_index", "parse_answer", "parse_instruction", "with_stop_and_backtrack",
]
