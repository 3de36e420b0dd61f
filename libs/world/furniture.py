"""The furniture of the procedural houses, as a catalogue: label, colours, sizes, placement, shape.

A part is ``("box", (x0, y0, z0), (x1, y1, z1), rgb, label)`` or
``("cyl", (x, y), r, z0, z1, rgb, label, r_top)`` in the item frame: x along the wall (-w/2..w/2),
y away from the wall (0..d), z up. ``ROOM_FURNITURE`` lists what each room type holds, essentials
first.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

COLOURS: dict[str, tuple[float, float, float]] = {
    "red": (0.78, 0.16, 0.14),
    "green": (0.20, 0.62, 0.22),
    "blue": (0.18, 0.32, 0.78),
    "yellow": (0.92, 0.80, 0.18),
    "orange": (0.93, 0.50, 0.12),
    "purple": (0.52, 0.26, 0.66),
    "pink": (0.92, 0.55, 0.68),
    "white": (0.93, 0.93, 0.91),
    "black": (0.10, 0.10, 0.11),
    "grey": (0.50, 0.51, 0.53),
    "brown": (0.48, 0.31, 0.17),
    "beige": (0.85, 0.77, 0.60),
    "silver": (0.75, 0.77, 0.80),
    "teal": (0.10, 0.55, 0.55),
}


def colour_rgb(name_or_rgb) -> tuple[float, float, float]:
    return COLOURS[name_or_rgb] if isinstance(name_or_rgb, str) else name_or_rgb


def _legs(w, d, h, t, col, label, inset=0.03):
    xs = (-w / 2 + inset, w / 2 - inset - t)
    ys = (inset, d - inset - t)
    return [("box", (x, y, 0.0), (x + t, y + t, h), col, label) for x in xs for y in ys]


# --- the furniture catalogue ------------------------------------------------------------------
# Each kind's geometry is a small builder: (width, depth, height, colour rgb, rng) -> (parts, depth,
# height), the last two the footprint depth and height it really occupies (handles stick out). The
# catalogue below holds what varies by data: label, the colours and widths to draw from, the base
# depth and height, and where the piece stands.


def _bed(w, d, h, col, rng):
    return [
        ("box", (-w / 2, 0, 0), (w / 2, d, 0.3), colour_rgb("brown"), "bed"),
        ("box", (-w / 2 + 0.03, 0.05, 0.3), (w / 2 - 0.03, d - 0.03, 0.5), colour_rgb("white"), "bed"),
        ("box", (-w / 2 + 0.02, 0.55, 0.5), (w / 2 - 0.02, d - 0.02, 0.56), col, "bed"),
        ("box", (-w / 2 + 0.1, 0.08, 0.5), (w / 2 - 0.1, 0.45, 0.62), colour_rgb("white"), "bed"),
        ("box", (-w / 2, 0, 0), (w / 2, 0.06, 1.0), colour_rgb("brown"), "bed"),
    ], d, h


def _sofa(w, d, h, col, rng):
    return [
        ("box", (-w / 2, 0, 0.05), (w / 2, d, 0.42), col, "sofa"),
        ("box", (-w / 2, 0, 0.42), (w / 2, 0.22, 0.85), col, "sofa"),
        ("box", (-w / 2, 0.22, 0.42), (-w / 2 + 0.18, d, 0.62), col, "sofa"),
        ("box", (w / 2 - 0.18, 0.22, 0.42), (w / 2, d, 0.62), col, "sofa"),
        ("box", (-w / 2 + 0.2, 0.24, 0.42), (w / 2 - 0.2, d - 0.02, 0.5), colour_rgb("white"), "sofa"),
    ] + _legs(w, d, 0.05, 0.05, colour_rgb("black"), "sofa"), d, h


def _armchair(w, d, h, col, rng):
    return [
        ("box", (-w / 2, 0, 0.05), (w / 2, d, 0.42), col, "armchair"),
        ("box", (-w / 2, 0, 0.42), (w / 2, 0.2, 0.9), col, "armchair"),
        ("box", (-w / 2, 0.2, 0.42), (-w / 2 + 0.15, d, 0.62), col, "armchair"),
        ("box", (w / 2 - 0.15, 0.2, 0.42), (w / 2, d, 0.62), col, "armchair"),
    ] + _legs(w, d, 0.05, 0.05, colour_rgb("black"), "armchair"), d, h


def _table(w, d, h, col, rng):
    return [("box", (-w / 2, 0, h - 0.04), (w / 2, d, h), col, "table")] + _legs(w, d, h - 0.04, 0.05, col, "table"), d, h


def chair_parts(w, d, col):
    parts = [("box", (-w / 2, 0, 0.42), (w / 2, d, 0.46), col, "chair"), ("box", (-w / 2, 0, 0.46), (w / 2, 0.05, 0.9), col, "chair")]
    return parts + _legs(w, d, 0.42, 0.04, col, "chair", inset=0.0)


def _chair(w, d, h, col, rng):
    return chair_parts(w, d, col), d, h


def _fridge(w, d, h, col, rng):
    return [
        ("box", (-w / 2, 0, 0), (w / 2, d, h), col, "fridge"),
        ("box", (-w / 2 + 0.02, d, 1.15), (w / 2 - 0.02, d + 0.005, 1.16), colour_rgb("black"), "fridge"),
        ("box", (w / 2 - 0.1, d, 1.2), (w / 2 - 0.07, d + 0.04, 1.6), colour_rgb("grey"), "fridge"),
        ("box", (w / 2 - 0.1, d, 0.7), (w / 2 - 0.07, d + 0.04, 1.05), colour_rgb("grey"), "fridge"),
    ], d + 0.04, h


def _stove(w, d, h, col, rng):
    parts = [
        ("box", (-w / 2, 0, 0), (w / 2, d, h - 0.02), col, "stove"),
        ("box", (-w / 2, 0, h - 0.02), (w / 2, d, h), colour_rgb("black"), "stove"),
        ("box", (-w / 2 + 0.05, d, 0.15), (w / 2 - 0.05, d + 0.01, 0.6), colour_rgb("black"), "stove"),
        ("box", (-w / 2, 0, h), (w / 2, 0.05, h + 0.12), col, "stove"),
    ]
    for bx in (-0.14, 0.14):
        for by in (0.18, 0.42):
            parts.append(("cyl", (bx, by), 0.09, h, h + 0.015, colour_rgb("grey"), "stove", None))
    return parts, d + 0.01, h + 0.12


def _kitchen_counter(w, d, h, col, rng):
    return [
        ("box", (-w / 2, 0, 0), (w / 2, d - 0.02, h - 0.04), col, "kitchen counter"),
        ("box", (-w / 2, 0, h - 0.04), (w / 2, d, h), colour_rgb("grey"), "kitchen counter"),
        ("box", (-0.25, 0.1, h - 0.005), (0.25, 0.5, h + 0.002), colour_rgb("silver"), "sink"),
        ("cyl", (0.0, 0.06), 0.02, h, h + 0.3, colour_rgb("silver"), "sink", None),
    ], d, h


def _sink(w, d, h, col, rng):
    return [
        ("box", (-0.1, 0, 0), (0.1, 0.25, h - 0.15), col, "sink"),
        ("box", (-w / 2, 0, h - 0.15), (w / 2, d, h), col, "sink"),
        ("box", (-w / 2 + 0.05, 0.05, h), (w / 2 - 0.05, d - 0.05, h + 0.005), colour_rgb("silver"), "sink"),
        ("box", (-0.2, 0, 1.1), (0.2, 0.02, 1.6), colour_rgb("silver"), "mirror"),
    ], d, h


def _toilet(w, d, h, col, rng):
    return [
        ("box", (-0.2, 0, 0.4), (0.2, 0.2, 0.8), col, "toilet"),
        ("cyl", (0.0, 0.45), 0.14, 0.0, 0.38, col, "toilet", 0.2),
        ("cyl", (0.0, 0.45), 0.2, 0.38, 0.42, col, "toilet", None),
    ], d, h


def _bathtub(w, d, h, col, rng):
    t = 0.08
    return [
        ("box", (-w / 2, 0, 0), (w / 2, d, 0.1), col, "bathtub"),
        ("box", (-w / 2, 0, 0.1), (w / 2, t, h), col, "bathtub"),
        ("box", (-w / 2, d - t, 0.1), (w / 2, d, h), col, "bathtub"),
        ("box", (-w / 2, t, 0.1), (-w / 2 + t, d - t, h), col, "bathtub"),
        ("box", (w / 2 - t, t, 0.1), (w / 2, d - t, h), col, "bathtub"),
        ("box", (-w / 2 + t, t, 0.1), (w / 2 - t, d - t, 0.35), colour_rgb("blue"), "bathtub"),
    ], d, h


def _washing_machine(w, d, h, col, rng):
    # The door would be a cylinder lying on the front: a thin box stands in for it.
    return [("box", (-w / 2, 0, 0), (w / 2, d, h), col, "washing machine"),
            ("box", (-0.18, d, 0.27), (0.18, d + 0.02, 0.63), colour_rgb("grey"), "washing machine")], d + 0.02, h


def _desk(w, d, h, col, rng):
    parts = [("box", (-w / 2, 0, h - 0.04), (w / 2, d, h), col, "desk"), ("box", (w / 2 - 0.45, 0.02, 0), (w / 2, d - 0.02, h - 0.04), col, "desk")]
    parts += [("box", (-w / 2, 0.02, 0), (-w / 2 + 0.04, d - 0.02, h - 0.04), col, "desk")]
    parts += [("box", (-0.25, 0.05, h), (0.25, 0.08, h + 0.35), colour_rgb("black"), "monitor"), ("box", (-0.03, 0.08, h), (0.03, 0.14, h + 0.1), colour_rgb("black"), "monitor")]
    return parts, d, h + 0.35


BOOK_COLOURS = ("red", "blue", "green", "yellow", "orange", "purple", "white")


def _bookshelf(w, d, h, col, rng):
    parts = [
        ("box", (-w / 2, 0, 0), (w / 2, 0.02, h), col, "bookshelf"),
        ("box", (-w / 2, 0, 0), (-w / 2 + 0.03, d, h), col, "bookshelf"),
        ("box", (w / 2 - 0.03, 0, 0), (w / 2, d, h), col, "bookshelf"),
    ]
    book_cols = [colour_rgb(n) for n in BOOK_COLOURS]
    for k in range(5):
        z = k * (h - 0.03) / 4
        parts.append(("box", (-w / 2, 0, z), (w / 2, d, z + 0.03), col, "bookshelf"))
        if k < 4:
            x = -w / 2 + 0.04
            while x < w / 2 - 0.08:
                bw = float(rng.uniform(0.03, 0.07))
                bh = float(rng.uniform(0.2, 0.33))
                parts.append(("box", (x, 0.04, z + 0.03), (x + bw, d - 0.03, z + 0.03 + bh), book_cols[int(rng.integers(len(book_cols)))], "book"))
                x += bw + 0.005
    return parts, d, h


def _plant(w, d, h, pot, rng):
    r = w / 2
    return [
        ("cyl", (0.0, r), 0.16, 0.0, 0.35, pot, "plant pot", 0.2),
        ("cyl", (0.0, r), 0.03, 0.35, 0.7, colour_rgb("brown"), "plant", None),
        ("cyl", (0.0, r), 0.08, 0.55, 0.75, colour_rgb("green"), "plant", r),
        ("cyl", (0.0, r), r, 0.75, 1.05, colour_rgb("green"), "plant", 0.15),
        ("cyl", (0.0, r), 0.15, 1.05, 1.25, colour_rgb("green"), "plant", 0.0),
    ], d, h


def _tv(w, d, h, col, rng):
    return [
        ("box", (-w / 2, 0, 0), (w / 2, d, 0.5), col, "tv stand"),
        ("box", (-0.55, 0.12, 0.5), (0.55, 0.17, 1.2), colour_rgb("black"), "tv"),
        ("box", (-0.52, 0.171, 0.53), (0.52, 0.175, 1.17), (0.15, 0.2, 0.3), "tv"),
    ], d, h


def _wardrobe(w, d, h, col, rng):
    return [
        ("box", (-w / 2, 0, 0), (w / 2, d, h), col, "wardrobe"),
        ("box", (-0.005, d, 0.05), (0.005, d + 0.005, h - 0.05), colour_rgb("black"), "wardrobe"),
        ("box", (-0.08, d, 1.0), (-0.06, d + 0.03, 1.3), colour_rgb("silver"), "wardrobe"),
        ("box", (0.06, d, 1.0), (0.08, d + 0.03, 1.3), colour_rgb("silver"), "wardrobe"),
    ], d + 0.03, h


def _nightstand(w, d, h, col, rng):
    return [
        ("box", (-w / 2, 0, 0), (w / 2, d, 0.5), col, "nightstand"),
        ("cyl", (0.0, 0.22), 0.06, 0.5, 0.85, colour_rgb("yellow"), "lamp", 0.1),
    ], d, h


def _lamp(w, d, h, col, rng):
    return [
        ("cyl", (0.0, 0.2), 0.15, 0.0, 0.03, colour_rgb("black"), "lamp", None),
        ("cyl", (0.0, 0.2), 0.015, 0.03, 1.45, colour_rgb("black"), "lamp", None),
        ("cyl", (0.0, 0.2), 0.2, 1.4, 1.7, col, "lamp", 0.12),
    ], d, h


def _cabinet(w, d, h, col, rng):
    return [("box", (-w / 2, 0, 0), (w / 2, d, h), col, "cabinet"), ("box", (-0.005, d, 0.05), (0.005, d + 0.005, h - 0.05), colour_rgb("black"), "cabinet")], d + 0.005, h


def _rug(w, d, h, col, rng):
    return [("box", (-w / 2, 0, 0), (w / 2, d, h), col, "rug")], d, h


def _painting(w, d, h, col, rng):
    return [
        ("box", (-w / 2, 0, 1.3), (w / 2, 0.03, 1.3 + 0.7 * w), colour_rgb("black"), "painting"),
        ("box", (-w / 2 + 0.04, 0.03, 1.34), (w / 2 - 0.04, d, 1.26 + 0.7 * w), col, "painting"),
    ], d, 1.3 + 0.7 * w


@dataclass(frozen=True)
class Furniture:
    """One kind of furniture: its label, how it is coloured and sized, where it stands, its shape.

    ``colours`` are drawn from (one colour name) unless there is only one; ``widths_m`` likewise.
    ``described_as`` overrides the colour name an instruction uses (a plant is "green" whatever its
    pot). ``placement``: ``wall`` (back to a wall), ``on wall`` (hung), ``centre``.
    """

    label: str
    colours: tuple[str, ...]
    widths_m: tuple[float, ...]
    depth_m: float
    height_m: float
    placement: str
    build: Callable
    described_as: str | None = None


_WOOD = ("brown", "white", "black", "beige")
FURNITURE: dict[str, Furniture] = {
    "bed": Furniture("bed", ("blue", "red", "green", "purple", "beige", "grey"), (1.4, 1.6), 2.0, 1.0, "wall", _bed),
    "sofa": Furniture("sofa", ("red", "blue", "grey", "green", "orange", "beige"), (1.8, 2.1), 0.9, 0.85, "wall", _sofa),
    "armchair": Furniture("armchair", ("red", "blue", "yellow", "green", "purple"), (0.85,), 0.85, 0.9, "wall", _armchair),
    "table": Furniture("table", _WOOD, (1.2,), 0.8, 0.75, "centre", _table),
    "dining table": Furniture("table", _WOOD, (1.6,), 0.9, 0.75, "centre", _table),
    "kitchen table": Furniture("table", _WOOD, (1.1,), 0.75, 0.75, "centre", _table),
    "coffee table": Furniture("coffee table", _WOOD, (1.0,), 0.55, 0.42, "centre", _table),
    "chair": Furniture("chair", ("brown", "black", "white", "red", "blue"), (0.45,), 0.45, 0.9, "wall", _chair),
    "fridge": Furniture("fridge", ("white", "silver"), (0.7,), 0.7, 1.85, "wall", _fridge),
    "stove": Furniture("stove", ("silver",), (0.6,), 0.6, 0.9, "wall", _stove),
    "kitchen counter": Furniture("kitchen counter", ("white", "beige", "grey", "teal"), (1.2, 1.6), 0.6, 0.9, "wall",
                                 _kitchen_counter),
    "sink": Furniture("sink", ("white",), (0.55,), 0.45, 0.85, "wall", _sink),
    "toilet": Furniture("toilet", ("white",), (0.42,), 0.7, 0.8, "wall", _toilet),
    "bathtub": Furniture("bathtub", ("white",), (1.7,), 0.75, 0.55, "wall", _bathtub),
    "washing machine": Furniture("washing machine", ("white",), (0.6,), 0.6, 0.85, "wall", _washing_machine),
    "desk": Furniture("desk", ("white", "brown", "black"), (1.4,), 0.7, 0.75, "wall", _desk),
    "bookshelf": Furniture("bookshelf", ("brown", "white", "black"), (0.8, 1.0), 0.35, 1.9, "wall", _bookshelf),
    "plant": Furniture("plant", ("orange", "white", "grey", "brown"), (0.44,), 0.44, 1.25, "wall", _plant,
                       described_as="green"),
    "tv": Furniture("tv", ("black", "brown", "white"), (1.4,), 0.45, 1.2, "wall", _tv, described_as="black"),
    "wardrobe": Furniture("wardrobe", ("white", "brown", "grey"), (1.0, 1.4), 0.6, 2.0, "wall", _wardrobe),
    "nightstand": Furniture("nightstand", ("brown", "white"), (0.45,), 0.45, 0.85, "wall", _nightstand),
    "lamp": Furniture("lamp", ("yellow", "white", "orange"), (0.4,), 0.4, 1.7, "wall", _lamp),
    "cabinet": Furniture("cabinet", ("brown", "white", "teal", "grey"), (1.2,), 0.45, 0.85, "wall", _cabinet),
    "rug": Furniture("rug", ("red", "blue", "beige", "purple", "teal"), (2.0,), 1.4, 0.01, "centre", _rug),
    "painting": Furniture("painting", ("red", "blue", "yellow", "green", "orange"), (0.6, 0.9), 0.035, 0.0,
                          "on wall", _painting),
}


def _pick(rng: np.random.Generator, options: tuple):
    """One of ``options``; a single option costs no random draw (seeded houses depend on that)."""
    return options[0] if len(options) == 1 else rng.choice(list(options))


def furniture_item(kind: str, rng: np.random.Generator):
    """(label, colour name, width, depth, height, parts, placement) for a furniture kind."""
    f = FURNITURE.get(kind)
    if f is None:
        raise ValueError(f"unknown furniture kind {kind!r}")
    colour = str(_pick(rng, f.colours))
    w = float(_pick(rng, f.widths_m))
    parts, d, h = f.build(w, f.depth_m, f.height_m, colour_rgb(colour), rng)
    return f.label, f.described_as or colour, w, d, h, parts, f.placement


ROOM_FURNITURE: dict[str, list[str]] = {
    "bedroom": ["bed", "wardrobe", "nightstand", "plant", "desk", "painting", "lamp"],
    "kitchen": ["fridge", "stove", "kitchen counter", "kitchen table", "plant", "cabinet"],
    "bathroom": ["toilet", "sink", "bathtub", "washing machine", "plant"],
    "living room": ["sofa", "tv", "coffee table", "armchair", "plant", "bookshelf", "lamp", "rug", "painting"],
    "dining room": ["dining table", "cabinet", "plant", "painting", "lamp"],
    "office": ["desk", "bookshelf", "chair", "plant", "cabinet", "painting"],
    "hallway": ["plant", "painting", "cabinet"],
    "staircase": [],
}
