"""Instruction text: R2R-style descriptions of a path (rooms, turns, landmarks) and the vocabulary."""

from __future__ import annotations

import math
import re
from typing import Any

import numpy as np

from shared.geometry import wrap_angle

from ..scene import Scene


def _tokenize(text: str) -> list[str]:
    return re.findall(r"[a-z0-9]+|[.,]", text.lower())


def build_vocab(texts: list[str]) -> dict[str, Any]:
    """An ``instruction_vocab`` in the R2R-CE layout (pad 0, unk 1, then sorted words)."""
    words = ["<pad>", "<unk>"] + sorted({w for t in texts for w in _tokenize(t)})
    idx = {w: i for i, w in enumerate(words)}
    return {"word_list": words, "word2idx_dict": idx, "stoi": dict(idx), "itos": list(words), "num_vocab": len(words), "UNK_INDEX": 1, "PAD_INDEX": 0}


def tokens_for(text: str, vocab: dict[str, Any], length: int = 200) -> list[int]:
    idx = vocab["word2idx_dict"]
    toks = [idx.get(w, vocab["UNK_INDEX"]) for w in _tokenize(text)][:length]
    return toks + [vocab["PAD_INDEX"]] * (length - len(toks))


def _turn_word(angle: float) -> str | None:
    a = math.degrees(float(wrap_angle(angle)))
    if abs(a) < 35:
        return None
    if abs(a) > 135:
        return "turn around"
    if abs(a) > 60:
        return "turn left" if a > 0 else "turn right"
    return "bear left" if a > 0 else "bear right"


def describe_path(scene: Scene, path_m: np.ndarray, start_heading_rad: float, goal_object=None) -> str:
    """An R2R-style instruction from the path's rooms, turns and landmarks."""
    pts = np.asarray(path_m, dtype=np.float64)
    dense = _resample(pts, 0.25)
    rooms = [scene.room_at(p) for p in dense]
    room_type = {r.name: r.room_type for r in scene.rooms}
    # Runs of the same room; the two storeys of a stairwell count as one; corners clipped for less
    # than ~0.5 m are not worth a sentence.
    key = [None if r is None else ("staircase" if r.room_type == "staircase" else r.name) for r in rooms]
    runs: list[list] = []
    for i, k in enumerate(key):
        if k is None:
            continue
        if runs and runs[-1][0] == k:
            runs[-1][2] = i + 1
        else:
            runs.append([k, i, i + 1])
    runs = [r for j, r in enumerate(runs) if r[2] - r[1] >= 3 or j in (0, len(runs) - 1)]
    merged: list[list] = []
    for r in runs:
        if merged and merged[-1][0] == r[0]:
            merged[-1][2] = r[2]
        else:
            merged.append(list(r))
    seq = [(("staircase" if k == "staircase" else k), i0) for k, i0, _ in merged]
    room_type.setdefault("staircase", "staircase")
    seq_end = [i1 for _, _, i1 in merged]
    sentences: list[str] = []
    if len(pts) > 1:
        d0 = pts[1] - pts[0]
        first_dir = math.atan2(d0[1], d0[0])
    else:
        first_dir = start_heading_rad
    turn0 = _turn_word(first_dir - start_heading_rad)
    if seq:
        t0 = room_type[seq[0][0]]
        if len(seq) > 1:
            lead = f"{turn0.capitalize()} and exit the {t0}" if turn0 else f"Exit the {t0}"
        else:
            lead = f"{turn0.capitalize()} and walk through the {t0}" if turn0 else f"Walk through the {t0}"
        sentences.append(lead)
    used: set[int] = set()
    if goal_object is not None:
        used.add(goal_object.object_id)
    for k, (name, i0) in enumerate(seq[1:], start=1):
        seg = dense[i0 : seq_end[k]]
        # The turn taken on entering this room.
        turn = None
        if i0 >= 2 and i0 + 2 < len(dense):
            before = dense[i0] - dense[i0 - 2]
            after = dense[min(i0 + 4, len(dense) - 1)] - dense[i0]
            turn = _turn_word(math.atan2(after[1], after[0]) - math.atan2(before[1], before[0]))
        rt = room_type[name]
        prev_rt = room_type[seq[k - 1][0]]
        the = "the next" if rt == prev_rt else "the"
        if rt == "staircase":
            z0, z1 = dense[i0][2], dense[max(seq_end[k] - 1, i0)][2]
            phrase = "go up the stairs" if z1 > z0 else "go down the stairs"
        elif k == len(seq) - 1:
            phrase = f"enter {the} {rt}"
        else:
            phrase = f"go through {the} {rt}"
        if turn:
            phrase = f"{turn} and {phrase}"
        # A landmark passed in this room.
        mark = _landmark(scene, seg, name, used)
        if mark is not None and k < len(seq) - 1:
            phrase += f", walking past the {mark.description}"
            used.add(mark.object_id)
        sentences.append(phrase[0].upper() + phrase[1:])
    if goal_object is not None:
        goal_room = room_type.get(goal_object.room, "room")
        sentences.append(f"Stop next to the {goal_object.description} in the {goal_room}")
    else:
        last = room_type[seq[-1][0]] if seq else "room"
        sentences.append(f"Stop in the {last}")
    return ". ".join(sentences) + "."


def _landmark(scene: Scene, seg: np.ndarray, room: str, used: set[int]):
    best, best_d = None, 1.5
    for o in scene.objects:
        if o.room != room or o.object_id in used or o.label in ("painting", "rug", "chair"):
            continue
        if len(seg) == 0:
            continue
        d = float(np.min(np.linalg.norm(seg[:, :2] - np.array(o.position_m[:2]), axis=1)))
        if d < best_d:
            best, best_d = o, d
    return best


def _resample(pts: np.ndarray, spacing_m: float) -> np.ndarray:
    if len(pts) < 2:
        return pts.copy()
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    s = np.r_[0.0, np.cumsum(seg)]
    n = max(2, int(np.ceil(s[-1] / spacing_m)) + 1)
    q = np.linspace(0.0, s[-1], n)
    return np.column_stack([np.interp(q, s, pts[:, i]) for i in range(3)])
