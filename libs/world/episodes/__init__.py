"""R2R-CE / RxR-CE episodes: the file format, the oracle that follows a path, instruction text, and
generation in procedural houses; one module each, everything re-exported here.

* :mod:`.format` - :class:`Episode`, :class:`EpisodeDataset`, :class:`GroundTruth`, exact read/write
  (the one place episode positions are converted from Habitat's y-up frame);
* :mod:`.oracle` - :func:`follow_path` (VLN-CE's discrete shortest-path follower), :func:`ground_truth_for`;
* :mod:`.instructions` - :func:`describe_path`, :func:`build_vocab`, :func:`tokens_for`;
* :mod:`.generate` - :func:`generate_episodes`.
"""

from .format import (
    MOVE_FORWARD,
    STOP,
    TURN_LEFT,
    TURN_RIGHT,
    Episode,
    EpisodeDataset,
    GroundTruth,
    read_episodes,
    read_ground_truth,
    write_episodes,
    write_ground_truth,
)
from .generate import generate_episodes
from .instructions import build_vocab, describe_path, tokens_for
from .oracle import follow_path, ground_truth_for

__all__ = [
    "MOVE_FORWARD", "STOP", "TURN_LEFT", "TURN_RIGHT", "Episode", "EpisodeDataset", "GroundTruth", "build_vocab",
    "describe_path", "follow_path", "generate_episodes", "ground_truth_for", "read_episodes", "read_ground_truth",
    "tokens_for", "write_episodes", "write_ground_truth",
]
