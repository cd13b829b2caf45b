"""The synthetic scene presets: objects, materials, camera rigs and the edit each one ships with.

World units, +z up. Every surface is an object with an id (1, 2, ...; 0 is empty background), so the
ground-truth mask has an id wherever the depth is non-zero.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np

from repaint_nerf.core.synth import rigs

TEXTURES = ("plain", "checker", "stripes", "noise", "wood", "label")


@dataclass(frozen=True)
class SceneObject:
    """One object: a primitive mesh placed by translation + yaw, with a procedural material (Lambertian,
    plus optional fine photographic grain and a specular highlight)."""

    name: str
    mesh: str  # a key of core.synth.meshes.BUILDERS
    params: dict
    position: tuple[float, float, float]
    color: tuple[float, float, float]
    texture: str = "plain"  # one of TEXTURES
    texture_scale: float = 4.0  # pattern cycles per world unit
    color2: tuple[float, float, float] | None = None  # second texture colour; None = a darker `color`
    yaw: float = 0.0  # degrees about +z
    grain: float = 0.0  # amplitude of fine multiplicative noise on the albedo (0 = none)
    specular: float = 0.0  # strength of the white highlight (0 = matte)

    def second_color(self) -> tuple[float, float, float]:
        if self.color2 is not None:
            return self.color2
        return tuple(float(0.45 * c + 0.04) for c in self.color)


@dataclass(frozen=True)
class Edit:
    """The change that makes the edited variant: recolour object `target` or replace it by `replacement`."""

    kind: str  # "recolor" or "replace"
    target: str  # object name
    color: tuple[float, float, float] | None = None
    replacement: SceneObject | None = None
    description: str = ""


@dataclass
class SceneSpec:
    """A concrete scene: objects, camera rig, intrinsics and the edit."""

    name: str
    kind: str  # "bounded", "forward" or "unbounded"
    objects: list[SceneObject]
    edit: Edit
    rig: Callable[[int, np.random.Generator], np.ndarray]  # (n, rng) -> (n, 4, 4) c2w
    camera_angle_x: float
    opaque: bool  # every pixel has a surface; images are written as RGB
    near: float = 0.05
    far: float = 50.0
    extra: dict = field(default_factory=dict)

    def edited_objects(self) -> list[SceneObject]:
        """The objects of the edited variant (same ids and order; the target changed)."""
        out = []
        for obj in self.objects:
            if obj.name != self.edit.target:
                out.append(obj)
            elif self.edit.kind == "recolor":
                out.append(replace(obj, color=self.edit.color, color2=None))
            else:
                out.append(self.edit.replacement)
        return out

    def edited_id(self) -> int:
        """Object id (1-based position in `objects`) of the edited object."""
        return 1 + [o.name for o in self.objects].index(self.edit.target)


RED, GREEN, BLUE = (0.85, 0.12, 0.1), (0.15, 0.7, 0.2), (0.12, 0.3, 0.9)
YELLOW, ORANGE, PURPLE = (0.92, 0.8, 0.15), (0.95, 0.5, 0.1), (0.55, 0.2, 0.75)
GREY, LIGHT = (0.6, 0.6, 0.58), (0.82, 0.8, 0.76)


def _floor(radius: float = 1.6) -> SceneObject:
    return SceneObject("floor", "disc", {"radius": radius}, (0.0, 0.0, 0.0), LIGHT, "checker", 3.0,
                       color2=(0.35, 0.35, 0.38))


def _centre_objects() -> list[SceneObject]:
    """Four primitives on a ring, resting on z = 0 (the demo layout)."""
    return [
        SceneObject("sphere", "sphere", {"radius": 0.42}, (0.7, 0.35, 0.42), RED, "checker", 5.0),
        SceneObject("cube", "box", {"sx": 0.62, "sy": 0.62, "sz": 0.62}, (-0.55, 0.6, 0.31), GREEN,
                    "stripes", 6.0, yaw=25.0),
        SceneObject("cylinder", "cylinder", {"radius": 0.28, "height": 0.9}, (-0.6, -0.55, 0.45), ORANGE,
                    "noise", 6.0),
        SceneObject("torus", "torus", {"major": 0.34, "minor": 0.13}, (0.45, -0.7, 0.13), PURPLE,
                    "checker", 7.0),
    ]


def _spread_out(objs: list[SceneObject]) -> list[SceneObject]:
    """The demo primitives rearranged across the view of a forward-facing rig (none hides another)."""
    xy = {"sphere": (0.62, 0.15), "cube": (-0.8, 0.5), "cylinder": (-0.05, 0.9), "torus": (0.1, -0.7)}
    return [replace(o, position=(*xy[o.name], o.position[2])) for o in objs]


def _demo() -> SceneSpec:
    return SceneSpec(
        "demo", "bounded", [_floor(), *_centre_objects()],
        Edit("recolor", "sphere", color=BLUE, description="the red sphere becomes blue"),
        rigs.hemisphere(radius=4.2, target=(0.0, 0.0, 0.3)), 0.75, opaque=False)


def _similar() -> SceneSpec:
    reds = [(0.85, 0.2, 0.15), (0.8, 0.25, 0.2), (0.88, 0.22, 0.2), (0.82, 0.18, 0.17)]
    textures = ["checker", "stripes", "noise", "plain"]
    objs = [replace(o, color=c, texture=t, color2=None) for o, c, t in zip(_centre_objects(), reds, textures)]
    return SceneSpec(
        "similar", "bounded", [_floor(), *objs],
        Edit("recolor", "cube", color=GREEN, description="the red striped cube becomes green"),
        rigs.hemisphere(radius=4.2, target=(0.0, 0.0, 0.3)), 0.75, opaque=False)


def _thin() -> SceneSpec:
    objs = [
        _floor(),
        SceneObject("pole", "cylinder", {"radius": 0.03, "height": 1.4}, (0.2, 0.1, 0.7), RED, "stripes", 8.0),
        SceneObject("ball", "sphere", {"radius": 0.1}, (-0.45, 0.35, 0.1), YELLOW, "plain"),
        SceneObject("cube", "box", {"sx": 0.55, "sy": 0.55, "sz": 0.55}, (-0.35, -0.6, 0.275), BLUE,
                    "checker", 6.0, yaw=15.0),
        SceneObject("torus", "torus", {"major": 0.3, "minor": 0.1}, (0.7, -0.4, 0.1), GREEN, "noise", 7.0),
    ]
    return SceneSpec(
        "thin", "bounded", objs,
        Edit("recolor", "pole", color=BLUE, description="the thin red pole becomes blue"),
        rigs.hemisphere(radius=4.2, target=(0.0, 0.0, 0.4)), 0.75, opaque=False)


def _forward() -> SceneSpec:
    objs = [
        # Just large enough to fill every view of the rig below (the aabb stays tight).
        SceneObject("wall", "box", {"sx": 8.0, "sy": 0.2, "sz": 5.0}, (0.0, 2.1, 1.5), LIGHT, "noise", 2.5,
                    color2=(0.45, 0.42, 0.5)),
        SceneObject("floor", "box", {"sx": 8.0, "sy": 5.0, "sz": 0.2}, (0.0, -0.3, -0.1), GREY, "checker", 2.0,
                    color2=(0.3, 0.3, 0.33)),
        *_spread_out(_centre_objects()),
    ]
    return SceneSpec(
        "forward", "forward", objs,
        Edit("recolor", "sphere", color=BLUE, description="the red sphere becomes blue"),
        rigs.forward_plane(center=(0.0, -3.2, 1.0), target=(0.0, 0.3, 0.4), extent=(0.6, 0.35)), 0.9,
        opaque=True)


def _room360() -> SceneSpec:
    # The walls reach past the floor and ceiling discs so the room is closed without slivers.
    objs = [
        SceneObject("floor", "disc", {"radius": 5.05}, (0.0, 0.0, 0.0), LIGHT, "checker", 2.0,
                    color2=(0.35, 0.35, 0.38)),
        SceneObject("walls", "cylinder", {"radius": 5.0, "height": 4.2, "inward": True, "caps": False},
                    (0.0, 0.0, 2.0), (0.7, 0.75, 0.85), "stripes", 1.5, color2=(0.35, 0.4, 0.55)),
        SceneObject("ceiling", "disc", {"radius": 5.05}, (0.0, 0.0, 4.0), (0.9, 0.88, 0.8), "noise", 1.5),
        *_centre_objects(),
    ]
    return SceneSpec(
        "room360", "unbounded", objs,
        Edit("recolor", "sphere", color=BLUE, description="the red sphere becomes blue"),
        rigs.ring(radius=2.6, heights=(0.9, 1.8), target=(0.0, 0.0, 0.35)), 1.0, opaque=True)


def _replace() -> SceneSpec:
    spec = _demo()
    cube = next(o for o in spec.objects if o.name == "cube")
    cone = replace(cube, name="cone", mesh="cone", params={"radius": 0.36, "height": 0.8},
                   position=(cube.position[0], cube.position[1], 0.4))
    spec.name = "replace"
    spec.edit = Edit("replace", "cube", replacement=cone,
                     description="the green striped cube is replaced by a green striped cone")
    return spec


# The hard presets (issue 15): photo-like textures, supports of a similar colour, touching neighbours of the
# same hue, highlights and clutter; each edits the object a user would drag a patch on.
WOOD_DARK, WOOD_DARK2 = (0.42, 0.28, 0.17), (0.27, 0.17, 0.1)
CRUST, CRUST2 = (0.78, 0.53, 0.27), (0.6, 0.37, 0.17)
BOARD, BOARD2 = (0.74, 0.55, 0.33), (0.58, 0.4, 0.22)


def _clutter(ring: float, z0: float = 0.0) -> list[SceneObject]:
    """Small everyday objects around the scene's edge: a cluttered background of mixed colours."""
    return [
        SceneObject("mug", "cylinder", {"radius": 0.14, "height": 0.3}, (ring * 0.75, ring * 0.55, z0 + 0.15),
                    (0.9, 0.9, 0.86), "stripes", 9.0, color2=(0.2, 0.35, 0.7), grain=0.1, specular=0.4),
        SceneObject("bottle", "cylinder", {"radius": 0.11, "height": 0.6}, (-ring * 0.8, ring * 0.5, z0 + 0.3),
                    (0.15, 0.45, 0.22), "noise", 12.0, grain=0.15, specular=0.7),
        SceneObject("apple", "sphere", {"radius": 0.15}, (ring * 0.7, -ring * 0.6, z0 + 0.15), (0.75, 0.12, 0.1),
                    "noise", 9.0, color2=(0.85, 0.6, 0.15), grain=0.2, specular=0.3),
        SceneObject("tin", "box", {"sx": 0.28, "sy": 0.2, "sz": 0.12}, (-ring * 0.7, -ring * 0.7, z0 + 0.06),
                    (0.25, 0.3, 0.6), "label", 16.0, color2=(0.9, 0.85, 0.7), yaw=30.0, grain=0.1),
    ]


def _bread() -> SceneSpec:
    objs = [
        SceneObject("table", "disc", {"radius": 1.7}, (0.0, 0.0, 0.0), WOOD_DARK, "wood", 3.0, color2=WOOD_DARK2,
                    grain=0.15),
        SceneObject("board", "box", {"sx": 1.5, "sy": 0.95, "sz": 0.08}, (0.0, 0.0, 0.04), BOARD, "wood", 5.0,
                    color2=BOARD2, yaw=8.0, grain=0.2, specular=0.05),
        SceneObject("loaf", "ellipsoid", {"rx": 0.5, "ry": 0.3, "rz": 0.22}, (0.05, 0.02, 0.3), CRUST, "noise", 5.0,
                    color2=CRUST2, yaw=8.0, grain=0.3, specular=0.08),
        SceneObject("knife", "box", {"sx": 0.55, "sy": 0.05, "sz": 0.02}, (0.1, -0.38, 0.09), (0.72, 0.72, 0.74),
                    "plain", yaw=8.0, grain=0.05, specular=0.9),
        *_clutter(1.25),
    ]
    return SceneSpec(
        "bread", "bounded", objs,
        Edit("recolor", "loaf", color=(0.35, 0.2, 0.1), description="the golden loaf becomes dark rye"),
        rigs.hemisphere(radius=4.2, target=(0.0, 0.0, 0.25)), 0.75, opaque=False)


def _lemon() -> SceneSpec:
    lemon_y, box_y = (0.93, 0.8, 0.18), (0.95, 0.83, 0.22)
    objs = [
        SceneObject("table", "disc", {"radius": 1.7}, (0.0, 0.0, 0.0), (0.8, 0.78, 0.72), "noise", 2.5,
                    color2=(0.7, 0.66, 0.6), grain=0.15),
        SceneObject("tray", "box", {"sx": 1.8, "sy": 1.2, "sz": 0.06}, (0.0, 0.0, 0.03), (0.63, 0.64, 0.66),
                    "noise", 8.0, color2=(0.52, 0.53, 0.56), grain=0.12, specular=0.6),
        SceneObject("lemon", "ellipsoid", {"rx": 0.3, "ry": 0.22, "rz": 0.22}, (0.12, -0.1, 0.28), lemon_y,
                    "noise", 10.0, color2=(0.86, 0.7, 0.12), grain=0.3, specular=0.35),
        # a box of the same yellow with printed text, touching the lemon's side
        SceneObject("box", "box", {"sx": 0.55, "sy": 0.5, "sz": 0.7}, (-0.455, -0.05, 0.41), box_y, "label", 9.0,
                    color2=(0.55, 0.12, 0.08), grain=0.1),
        SceneObject("orange", "sphere", {"radius": 0.2}, (0.6, 0.4, 0.26), (0.95, 0.55, 0.1), "noise", 12.0,
                    color2=(0.85, 0.45, 0.08), grain=0.3, specular=0.3),
        *_clutter(1.35),
    ]
    return SceneSpec(
        "lemon", "bounded", objs,
        Edit("recolor", "lemon", color=(0.3, 0.75, 0.2), description="the lemon becomes a lime"),
        rigs.hemisphere(radius=4.2, target=(0.0, 0.0, 0.3)), 0.75, opaque=False)


def _toys() -> SceneSpec:
    can_red = (0.82, 0.12, 0.1)
    objs = [
        SceneObject("rug", "disc", {"radius": 1.6}, (0.0, 0.0, 0.0), (0.45, 0.5, 0.62), "noise", 7.0,
                    color2=(0.35, 0.38, 0.5), grain=0.25),
        SceneObject("can", "cylinder", {"radius": 0.22, "height": 0.62}, (0.0, 0.0, 0.31), can_red, "label", 10.0,
                    color2=(0.95, 0.93, 0.88), grain=0.08, specular=0.5),
        # a red toy block touching the can (same hue, another texture)
        SceneObject("block", "box", {"sx": 0.32, "sy": 0.32, "sz": 0.32}, (0.38, 0.0, 0.16), (0.85, 0.15, 0.12),
                    "plain", grain=0.1, yaw=10.0, specular=0.2),
        SceneObject("duck", "sphere", {"radius": 0.17}, (-0.33, 0.25, 0.17), (0.95, 0.82, 0.15), "plain",
                    grain=0.1, specular=0.4),
        SceneObject("cone", "cone", {"radius": 0.16, "height": 0.4}, (-0.15, -0.45, 0.2), (0.15, 0.35, 0.85),
                    "stripes", 10.0, grain=0.1),
        SceneObject("ring", "torus", {"major": 0.2, "minor": 0.07}, (0.5, 0.5, 0.07), (0.55, 0.2, 0.75),
                    "checker", 12.0, grain=0.1),
        SceneObject("ball", "sphere", {"radius": 0.12}, (0.62, -0.35, 0.12), (0.2, 0.7, 0.3), "checker", 14.0,
                    grain=0.1, specular=0.5),
        *_clutter(1.2),
    ]
    return SceneSpec(
        "toys", "bounded", objs,
        Edit("recolor", "can", color=(0.15, 0.35, 0.85), description="the red printed can becomes blue"),
        rigs.hemisphere(radius=4.2, target=(0.0, 0.0, 0.25)), 0.75, opaque=False)


def _occluded() -> SceneSpec:
    """A printed can in a ring of nearer toys, seen from a low table-top rig: from most viewpoints a toy of
    another colour covers part of the can (a duck in front of it in about a third of the views)."""
    can_red, duck_y = (0.8, 0.13, 0.12), (0.95, 0.8, 0.16)
    objs = [
        SceneObject("rug", "disc", {"radius": 1.3}, (0.0, 0.0, 0.0), (0.55, 0.5, 0.42), "noise", 6.0,
                    color2=(0.42, 0.38, 0.32), grain=0.25),
        SceneObject("can", "cylinder", {"radius": 0.2, "height": 0.66}, (0.0, 0.0, 0.33), can_red, "label", 10.0,
                    color2=(0.95, 0.93, 0.88), grain=0.08, specular=0.5),
        # the duck: a body and a head of one yellow, in front of the can from the rig's first azimuths
        SceneObject("duck", "ellipsoid", {"rx": 0.24, "ry": 0.17, "rz": 0.17}, (0.5, 0.05, 0.17), duck_y,
                    "noise", 14.0, color2=(0.9, 0.68, 0.1), grain=0.15, specular=0.35),
        SceneObject("duck_head", "sphere", {"radius": 0.11}, (0.55, 0.06, 0.4), duck_y, "noise", 14.0,
                    color2=(0.9, 0.68, 0.1), grain=0.15, specular=0.35),
        SceneObject("blocks", "box", {"sx": 0.26, "sy": 0.26, "sz": 0.44}, (-0.2, 0.42, 0.22), (0.2, 0.45, 0.85),
                    "checker", 10.0, color2=(0.9, 0.9, 0.85), yaw=20.0, grain=0.1),
        SceneObject("ball", "sphere", {"radius": 0.18}, (-0.42, -0.2, 0.18), (0.2, 0.65, 0.3), "stripes", 9.0,
                    color2=(0.95, 0.95, 0.9), grain=0.1, specular=0.5),
        SceneObject("cone", "cone", {"radius": 0.15, "height": 0.48}, (0.14, -0.42, 0.24), (0.55, 0.2, 0.75),
                    "stripes", 10.0, grain=0.1),
        *_clutter(0.95),
    ]
    return SceneSpec(
        "occluded", "bounded", objs,
        Edit("recolor", "can", color=(0.15, 0.35, 0.85), description="the red printed can behind the duck becomes blue"),
        rigs.hemisphere(radius=2.9, target=(0.0, 0.0, 0.22), elevation_deg=(8.0, 40.0)), 0.75, opaque=False)


PRESETS: dict[str, tuple[str, Callable[[], SceneSpec]]] = {
    "demo": ("four distinct-coloured primitives on a checker floor, 360 views, transparent background", _demo),
    "similar": ("four similar red primitives told apart by texture (checker, stripes, noise, plain)", _similar),
    "thin": ("a thin pole and a small ball beside larger objects", _thin),
    "forward": ("LLFF-like forward-facing capture of objects before a textured wall; opaque", _forward),
    "room360": ("360-degree capture inside a textured room, every pixel has a surface; opaque", _room360),
    "replace": ("the demo layout whose edited variant replaces the cube by a cone", _replace),
    "bread": ("hard: a grainy loaf on a wooden board of a similar brown, clutter around", _bread),
    "lemon": ("hard: a lemon touching a yellow printed box on a shiny metal tray, clutter around", _lemon),
    "toys": ("hard: a can with a printed label touching a red block, among toys on a rug", _toys),
    "occluded": ("hard: a printed can partly hidden behind a duck and other nearer toys in most views", _occluded),
}


def build_spec(name: str) -> SceneSpec:
    """The scene of preset `name` (a key of PRESETS); the layout is fixed, the seed only moves the cameras."""
    return PRESETS[name][1]()
