"""History compression, the prompt's form, saving, hashing and answer parsing."""

from __future__ import annotations

import base64
import json
import math

import cv2
import numpy as np
import pytest

from services.planner.core import (
    Ablation,
    ActionKind,
    ActionRecord,
    AnswerError,
    HistoryRecorder,
    PromptBuilder,
    StepContext,
    action_for,
    build_candidate_views,
    nearest_view_index,
    parse_answer,
    with_stop_and_backtrack,
)
from shared.geometry import panorama_headings
from shared.schemas import CameraIntrinsics, Candidate, CandidateKind, Panorama, Pose, RenderResult


def _img(v, px=64):
    return np.full((px, px, 3), v, np.uint8)


def test_history_merges_forward_runs_keeping_start_and_end():
    rec = HistoryRecorder()
    fwd = ActionRecord(ActionKind.FORWARD, 0.0, 1.5)
    turn = ActionRecord(ActionKind.TURN_MOVE, math.radians(90), 1.0)
    for step, action in enumerate([turn, fwd, fwd, fwd, turn, fwd, fwd]):
        rec.record(step, _img(step * 10, px=100), action)
    items = rec.compressed(current_rgb=_img(200, px=100), current_step=7)
    # o0 turn | o1 fwd x3 -> o4 turn | o5 fwd x2 -> current
    assert [i.step for i in items] == [0, 1, 4, 5, 7]
    assert items[1].action.kind == ActionKind.FORWARD and items[1].action.moves == 3
    assert items[1].action.distance_m == pytest.approx(4.5)
    assert items[3].action.moves == 2 and items[4].action is None
    assert all(i.image.shape == (256, 256, 3) for i in items)
    assert items[2].image[0, 0, 0] == 40  # the run's end observation is the one seen at step 4
    assert "4.5 m (3 moves)" in items[1].action.describe()
    # Without a current image the trailing run ends with its merged action.
    assert [i.step for i in rec.compressed()] == [0, 1, 4, 5]


def test_action_records_from_candidates():
    assert action_for(Candidate(index=0, angle_rad=0.1, distance_m=2.0)).kind == ActionKind.FORWARD
    assert action_for(Candidate(index=0, angle_rad=1.2, distance_m=2.0)).kind == ActionKind.TURN_MOVE
    assert action_for(Candidate(index=0, kind=CandidateKind.BACKTRACK, dx_m=1.0)).kind == ActionKind.BACKTRACK


def _context(anticipation=True, spatial_map=True, steps_of_history=3):
    pose = Pose(position_m=(1.0, 2.0, 0.0), heading_rad=0.3)
    heads = panorama_headings(pose.heading_rad)
    rgb = np.stack([_img(i * 20) for i in range(12)])
    pano = Panorama(pose=pose, camera=CameraIntrinsics(width_px=64, height_px=64), headings_rad=heads, rgb=rgb,
                    depth_m=np.ones((12, 64, 64), np.float32))
    wps = [Candidate(index=0, dx_m=2 * math.cos(0.3), dy_m=2 * math.sin(0.3), angle_rad=0.0, distance_m=2.0),
           Candidate(index=1, dx_m=2 * math.cos(0.3 - math.pi / 2), dy_m=2 * math.sin(0.3 - math.pi / 2),
                     angle_rad=-math.pi / 2, distance_m=2.0)]
    cands = with_stop_and_backtrack(wps, pose, (0.0, 2.0, 0.0))
    render = RenderResult(map_id="m", version=1, rgb=np.stack([_img(100 + k, 256) for k in range(3)]),
                          depth_m=np.ones((3, 256, 256), np.float32), hole_mask=np.zeros((3, 256, 256), bool))
    rec = HistoryRecorder()
    for s in range(steps_of_history):
        rec.record(s, _img(5 * s), ActionRecord(ActionKind.FORWARD, 0.0, 1.0))
    return StepContext(
        instruction="Go to the kitchen.", step=steps_of_history, pose=pose,
        candidates=build_candidate_views(cands, pano, render), history=rec.compressed(),
        spatial_map_rgb=_img(77, 128), ablation=Ablation(anticipation=anticipation, spatial_map=spatial_map),
        mission_id="m1",
    )


def test_candidates_get_backtrack_stop_and_nearest_observed_view():
    ctx = _context()
    kinds = [c.kind for c in ctx.candidates]
    assert kinds == [CandidateKind.WAYPOINT, CandidateKind.WAYPOINT, CandidateKind.BACKTRACK, CandidateKind.STOP]
    # Waypoint 1 is 90 deg to the right: panorama view 3 (views rotate right 30 deg each).
    assert ctx.candidates[0].observed_view_index == 0 and ctx.candidates[1].observed_view_index == 3
    assert nearest_view_index(panorama_headings(0.0), math.pi) == 6
    # The backtrack goes to (0, 2): world heading pi, i.e. view nearest heading pi from heading 0.3.
    assert ctx.candidates[2].observed_view_index == nearest_view_index(panorama_headings(0.3), math.pi)
    assert ctx.candidates[2].anticipated_rgb is not None and ctx.candidates[3].anticipated_rgb is None


def test_prompt_has_the_papers_form():
    prompt = PromptBuilder().build(_context())
    text = prompt.text()
    assert text.startswith("Instruction: Go to the kitchen.")
    assert text.count("-> if I took this action, I would partially imagine the next view: <image:cand") == 3
    assert "[observed view] <image:cand0_observed> [action: go straight 2.0 m]" in text
    assert "turn right 90 degrees and move 2.0 m" in text
    assert "go back to the previous position" in text and "Candidate 3: " in text
    assert "<image:spatial_map>" in text and '"action"' in text
    assert "move forward 3.0 m (3 moves)" in text  # the compressed history
    assert prompt.candidate_indices == [0, 1, 2, 3]
    msgs = prompt.to_openai_messages(image_format="png")
    urls = [p["image_url"]["url"] for p in msgs[1]["content"] if p["type"] == "image_url"]
    assert len(urls) == len(prompt.images())
    png = base64.b64decode(urls[0].split(",", 1)[1])
    decoded = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    assert decoded.shape == (256, 256, 3)


def test_ablations_remove_anticipation_and_map():
    text = PromptBuilder().build(_context(anticipation=False, spatial_map=False)).text()
    assert "imagine the next view" not in text and "spatial_map" not in text
    assert "[observed view]" in text


def test_prompt_digest_covers_images(tmp_path):
    a = _context()
    b = _context()
    assert PromptBuilder().build(a).digest() == PromptBuilder().build(b).digest()
    b.candidates[0].anticipated_rgb = b.candidates[0].anticipated_rgb.copy()
    b.candidates[0].anticipated_rgb[5, 5, 0] ^= 1  # one pixel bit
    assert PromptBuilder().build(a).digest() != PromptBuilder().build(b).digest()


def test_prompt_saves_for_inspection(tmp_path):
    prompt = PromptBuilder().build(_context())
    folder = prompt.save(tmp_path / "step_003")
    md = (folder / "prompt.md").read_text()
    saved = json.loads((folder / "messages.json").read_text())
    files = sorted((folder / "images").glob("*.png"))
    assert len(files) == len(prompt.images())
    assert saved["meta"]["digest"] == prompt.digest()
    for f in files:
        assert f"images/{f.name}" in md
        assert cv2.imread(str(f)) is not None


@pytest.mark.parametrize(
    "text,expected",
    [
        ('{"action": 2, "reasoning": "the kitchen is ahead"}', (2, "the kitchen is ahead")),
        ('Sure!\n```json\n{"action": "1", "reasoning": "x"}\n```', (1, "x")),
        ('{"action": 0}', (0, "")),
        ('{"action": "candidate 3", "reasoning": "stop"}', (3, "stop")),
    ],
)
def test_parse_valid_answers(text, expected):
    assert parse_answer(text, [0, 1, 2, 3]) == expected


@pytest.mark.parametrize(
    "text", ["", "I would go left.", '{"action": 7}', '{"reasoning": "x"}', '{"action": 1.5}', '{"action": true}',
             '{"action": 1,, }', '{"action": "left"}']
)
def test_parse_invalid_answers(text):
    with pytest.raises(AnswerError):
        parse_answer(text, [0, 1, 2, 3])


def test_context_rejects_duplicate_indices():
    from services.planner.core import ContextError

    pose = Pose(position_m=(0, 0, 0))
    c = build_candidate_views([Candidate(index=0), Candidate(index=0, kind=CandidateKind.STOP)], None)
    with pytest.raises(ContextError):
        StepContext(instruction="x", step=0, pose=pose, candidates=c)
