"""Scene-file frames, colours and semantics on small files written in the published formats."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from libs.world.errors import SceneFormatError
from services.robot_io.core.render import SceneRenderer
from services.robot_io.core.robot import SimConfig, SimRobot
from libs.world.scene import load_scene
from libs.world.scene_files import (
    FRAME_RULES,
    GLTF_Y_UP,
    Z_UP,
    SceneFrame,
    resolve_frame,
    split_scene_spec,
)
from shared.geometry import PinholeCamera, camera_pose, habitat_to_world

from .gltf_files import Primitive, box, write_glb, write_ply_with_face_ids


def _room_y_up(size_m=(6.0, 8.0), marker=(1.0, -2.0)) -> list[Primitive]:
    """A floor in a y-up file (x/z horizontal) and a 2 m tall marker post standing on it."""
    w, d = size_m
    floor_v = np.array([[-w / 2, 0, -d / 2], [w / 2, 0, -d / 2], [w / 2, 0, d / 2], [-w / 2, 0, d / 2]])
    floor_t = np.array([[0, 2, 1], [0, 3, 2]])  # normal +y in the file
    post_v, post_t = box((marker[0] - 0.1, 0.0, marker[1] - 0.1), (marker[0] + 0.1, 2.0, marker[1] + 0.1))
    return [Primitive(floor_v, floor_t, base_color=(0.1, 0.6, 0.2, 1.0)), Primitive(post_v, post_t, base_color=(0.9, 0.1, 0.1, 1.0))]


# --- frames ----------------------------------------------------------------------------------------


def test_spec_options_parse_and_reject_typos(tmp_path):
    assert split_scene_spec("a/b.glb") == ("a/b.glb", {})
    path, opts = split_scene_spec("/d/x.glb:up=z:scale=0.01:units_to_meters=2")
    assert path == "/d/x.glb" and opts == {"up": "z", "scale": "0.01", "units_to_meters": 2.0}
    assert split_scene_spec("x.glb:stage_config=/a/b.stage_config.json")[1] == {"stage_config": "/a/b.stage_config.json"}
    with pytest.raises(SceneFormatError, match="unknown scene option"):
        split_scene_spec("x.glb:upp=z")
    with pytest.raises(SceneFormatError):
        load_scene(str(write_glb(tmp_path / "r.glb", _room_y_up())) + ":up=q")
    with pytest.raises(SceneFormatError):
        load_scene(str(tmp_path / "r.glb") + ":up=y:front=y")  # parallel axes


@pytest.mark.parametrize(
    ("rel", "frame"),
    [
        ("mp3d/17DRP5sb8fy/17DRP5sb8fy.glb", Z_UP),
        ("scene_datasets/mp3d_example/17DRP5sb8fy/17DRP5sb8fy.glb", Z_UP),
        ("hm3d/val/00800-TEEsavR23oF/TEEsavR23oF.glb", Z_UP),
        ("x/TEEsavR23oF.basis.glb", Z_UP),
        ("objects/chair.glb", GLTF_Y_UP),
        ("objects/chair.gltf", GLTF_Y_UP),
        ("replica/office0/mesh.ply", Z_UP),
        ("scans/thing.obj", Z_UP),
    ],
)
def test_rule_table(tmp_path, rel, frame):
    assert resolve_frame(tmp_path / rel).frame == frame
    assert next(r for r in FRAME_RULES if r.matches(tmp_path / rel)).frame == frame


def test_precedence_explicit_then_stage_config_then_dataset_config_then_rules(tmp_path):
    scene = tmp_path / "hm3d" / "val" / "00001-abc" / "abc.glb"
    scene.parent.mkdir(parents=True)
    assert resolve_frame(scene).frame == Z_UP  # the rule
    (tmp_path / "hm3d" / "hm3d.scene_dataset_config.json").write_text(
        json.dumps({"stages": {"default_attributes": {"up": [0, 1, 0], "front": [0, 0, -1], "units_to_meters": 0.5}}}))
    r = resolve_frame(scene)
    assert r.frame == SceneFrame(units_to_meters=0.5) and r.source.endswith("hm3d.scene_dataset_config.json")
    # A stage config linked by render_asset, under another name, beats the dataset's defaults.
    (scene.parent / "stage.stage_config.json").write_text(json.dumps({"render_asset": "abc.glb", "up": [0, 0, 1], "scale": [2, 2, 2]}))
    r = resolve_frame(scene)
    assert r.frame.up == (0, 0, 1) and r.frame.front == (0, 1, 0) and r.frame.scale == (2, 2, 2)
    # An explicit override changes only what it names.
    r = resolve_frame(scene, {"scale": "3"})
    assert r.frame.scale == (3, 3, 3) and r.frame.up == (0, 0, 1) and r.source.startswith("explicit")
    # A new up axis without a front gets the usual front for it.
    assert resolve_frame(scene, {"up": "y"}).frame.front == (0, 0, -1)
    (scene.parent / "stage.stage_config.json").write_text("{not json")
    with pytest.raises(SceneFormatError, match="not a readable JSON"):
        resolve_frame(scene)


def test_y_up_glb_stands_upright_and_matches_habitat_to_world(tmp_path):
    path = write_glb(tmp_path / "room.glb", _room_y_up())
    scene = load_scene(str(path))
    lo, hi = scene.bounds_m
    assert lo[2] == pytest.approx(0.0) and hi[2] == pytest.approx(2.0)  # the floor at z=0, the post 2 m up
    assert hi[0] - lo[0] == pytest.approx(6.0) and hi[1] - lo[1] == pytest.approx(8.0)
    # The post at file (x=1, z=-2) is at world (1, 2): world y = -file z, like an R2R-CE position.
    top = scene.vertices[scene.vertices[:, 2] > 1.9]
    assert top[:, :2].mean(axis=0) == pytest.approx(habitat_to_world([1.0, 0.0, -2.0])[:2])
    robot = SimRobot(SimConfig(scene=str(path), camera={"width_px": 16, "height_px": 16}))
    assert robot.nav.reachable_area_m2 > 30
    assert robot.geodesic_distance((-2.0, -3.0, 0.0), (2.0, 3.0, 0.0)) < 8.0


def test_same_room_as_z_up_ply_and_as_y_up_glb_coincide(tmp_path):
    glb = load_scene(str(write_glb(tmp_path / "room.glb", _room_y_up())))
    ply = tmp_path / "room.ply"
    glb.export_ply(ply)
    again = load_scene(str(ply))
    assert np.allclose(again.vertices, glb.vertices, atol=1e-5)
    # And the same glb declared z-up lies on its side: the 8 m depth becomes the height.
    lo, hi = load_scene(f"{tmp_path / 'room.glb'}:up=z").bounds_m
    assert hi[2] - lo[2] == pytest.approx(8.0)


# --- colours ---------------------------------------------------------------------------------------


def _look_down(scene, at_xy, size=32):
    pose = camera_pose((at_xy[0], at_xy[1], 0.0), 0.0, math.radians(-89.0), 3.0)
    return SceneRenderer(scene).render(pose, PinholeCamera(size, size, 20.0))


def test_material_factors_vertex_colours_and_textures_in_one_scene(tmp_path):
    tex = np.zeros((8, 8, 3), np.uint8)
    tex[:4] = (250, 10, 10)  # glTF v < 0.5 is the image's top half
    tex[4:] = (10, 10, 250)
    a_v, a_t = box((-3, 0, -1), (-1, 0.1, 1))  # y-up file: thin slabs on the floor
    b_v, b_t = box((-1, 0, -1), (1, 0.1, 1))
    c_v, c_t = box((1, 0, -1), (3, 0.1, 1))
    prims = [
        Primitive(a_v, a_t, base_color=(0.2, 0.4, 0.8, 1.0)),
        Primitive(b_v, b_t, colors=np.tile([[1.0, 0.5, 0.0]], (8, 1)), base_color=(1.0, 1.0, 0.5, 1.0)),
        Primitive(c_v, c_t, uvs=np.tile([[0.5, 0.25]], (8, 1)), texture=tex, base_color=(0.5, 1.0, 1.0, 1.0)),
    ]
    scene = load_scene(str(write_glb(tmp_path / "three.glb", prims)))
    assert scene.texture is not None and len(scene.texture.images) == 1
    expect = {(-2.0, 0.0): (51, 102, 204), (0.0, 0.0): (255, 128, 0), (2.0, 0.0): (125, 10, 10)}
    for xy, rgb in expect.items():
        out = _look_down(scene, xy)
        px = out.rgb[out.depth_m > 0].reshape(-1, 3).astype(int)
        assert len(px) > 100
        assert np.abs(np.median(px, axis=0) - rgb).max() <= 2, f"at {xy}: {np.median(px, axis=0)} != {rgb}"


# --- semantics ---------------------------------------------------------------------------------------


def _mp3d_scan(root, with_semantic_ply=True):
    """A Matterport3D-layout scan (z-up, as MP3D glbs are): a floor, a bed, a lamp; two regions."""
    d = root / "mp3d" / "tiny1" / "tiny1.glb"
    fv = np.array([[0, 0, 0], [8, 0, 0], [8, 4, 0], [0, 4, 0]], float)
    ft = np.array([[0, 1, 2], [0, 2, 3]])
    bed_v, bed_t = box((1, 1, 0), (3, 2.5, 0.6))
    lamp_v, lamp_t = box((6, 1, 0), (6.3, 1.3, 1.5))
    write_glb(d, [Primitive(fv, ft), Primitive(bed_v, bed_t, base_color=(0.6, 0.2, 0.2, 1)), Primitive(lamp_v, lamp_t)])
    house = [
        "ASCII 1.1",
        "H tiny1 house 0 0 0 0 0 2 3 2 2 0 1  0 0 0 0 0  0 0 0 8 4 3  0 0 0 0 0",
        "L 0 2 - 4 2 0  0 0 0 8 4 3  0 0 0 0 0",
        "R 0 0 0 0 b 2 2 0  0 0 0 4 4 3  3  0 0 0 0",
        "R 1 0 0 0 l 6 2 0  4 0 0 8 4 3  3  0 0 0 0",
        "C 0 1 bed 11 bed 0 0 0 0 0",
        "C 1 2 table#lamp 14 lighting 0 0 0 0 0",
        "O 0 0 0 2 1.75 0.3  1 0 0  0 1 0  1.05 0.8 0.35  0 0 0 0 0 0 0 0",
        "O 1 1 1 6.15 1.15 0.75  1 0 0  0 1 0  0.2 0.2 0.8  0 0 0 0 0 0 0 0",
        "E 0 0 100 1.0 2 1.75 0.3 1 1 0 3 2.5 0.6 0 0 0 0 0",
        "E 1 1 101 0.5 6.15 1.15 0.75 6 1 0 6.3 1.3 1.5 0 0 0 0 0",
    ]
    d.with_name("tiny1.house").write_text("\n".join(house) + "\n")
    if with_semantic_ply:
        v = np.concatenate([fv, bed_v, lamp_v])
        t = np.concatenate([ft, bed_t + 4, lamp_t + 12])
        write_ply_with_face_ids(d.with_name("tiny1_semantic.ply"), v, t, object_id=np.r_[[-1, -1], [0] * 12, [1] * 12])
    return d


@pytest.mark.parametrize("with_semantic_ply", [True, False])
def test_mp3d_house_and_semantic_mesh_become_labels_rooms_objects(tmp_path, with_semantic_ply):
    _mp3d_scan(tmp_path, with_semantic_ply)
    scene = load_scene("mp3d/tiny1/tiny1.glb", tmp_path)
    # The MP3D rule: z-up, so the file's coordinates are the world's.
    assert scene.bounds_m[1][2] == pytest.approx(1.5)
    assert set(scene.label_names.values()) == {"bed", "lighting"}
    out = _look_down(scene, (2.0, 1.75))
    names = {scene.label_names[i] for i in np.unique(out.semantic) if i >= 0}
    assert names == {"bed"}
    out = _look_down(scene, (6.15, 1.15), size=16)
    lamp_top = (out.depth_m > 0) & (out.depth_m < 2.0)  # the lamp is 1.5 m tall, the camera 3 m up
    assert lamp_top.sum() > 5 and {scene.label_names[i] for i in np.unique(out.semantic[lamp_top])} == {"lighting"}
    floor = _look_down(scene, (5.0, 3.5), size=8)
    assert np.all(floor.semantic == -1)
    assert [(r.name, r.room_type) for r in scene.rooms] == [("bedroom 1", "bedroom"), ("living room 1", "living room")]
    assert scene.room_at((2.0, 2.0, 0.0)).room_type == "bedroom"
    bed = next(o for o in scene.objects if o.label == "bed")
    assert bed.room == "bedroom 1" and bed.position_m == pytest.approx((2.0, 1.75, -0.05)) and bed.size_m[0] == pytest.approx(2.1)


def test_hm3d_semantic_glb_and_txt_become_labels(tmp_path):
    d = tmp_path / "hm3d" / "minival" / "00800-tiny2" / "tiny2.glb"
    fv = np.array([[0, 0, 0], [6, 0, 0], [6, 6, 0], [0, 6, 0]], float)
    ft = np.array([[0, 1, 2], [0, 2, 3]])
    sofa_v, sofa_t = box((1, 1, 0), (3, 2, 0.8))
    write_glb(d, [Primitive(fv, ft), Primitive(sofa_v, sofa_t, base_color=(0.1, 0.3, 0.7, 1))])
    # The semantic mesh: the same geometry, each object one flat colour (here: the texture of HM3D v0.2).
    tex = np.zeros((2, 2, 3), np.uint8)
    tex[:, 0] = (0x9D, 0x4A, 0x57)  # left column: the floor
    tex[:, 1] = (0x1F, 0x77, 0xB4)  # right column: the sofa
    write_glb(d.with_name("tiny2.semantic.glb"), [
        Primitive(fv, ft, uvs=np.tile([[0.25, 0.5]], (4, 1)), texture=tex),
        Primitive(sofa_v, sofa_t, uvs=np.tile([[0.75, 0.5]], (8, 1)), texture=tex),
    ])
    d.with_name("tiny2.semantic.txt").write_text('HM3D Semantic Annotations\n1,9D4A57,"floor",0\n2,1F77B4,"sofa",0\n')
    scene = load_scene(str(d))
    assert set(scene.label_names.values()) == {"floor", "sofa"}
    sofa = _look_down(scene, (2.0, 1.5), size=8)
    assert {scene.label_names[i] for i in np.unique(sofa.semantic)} == {"sofa"}
    floor = _look_down(scene, (5.0, 5.0), size=8)
    assert {scene.label_names[i] for i in np.unique(floor.semantic)} == {"floor"}
    assert [o.label for o in scene.objects] == ["sofa"]  # the floor is structure, not a landmark
    assert scene.objects[0].position_m == pytest.approx((2.0, 1.5, 0.0))


def test_malformed_semantics_are_typed_errors(tmp_path):
    d = _mp3d_scan(tmp_path, with_semantic_ply=False)
    d.with_name("tiny1.house").write_text("ASCII 1.1\nO 0 0 zero\n")
    with pytest.raises(SceneFormatError, match="malformed"):
        load_scene(str(d))
    d.with_name("tiny1.house").write_text("not a house\n")
    with pytest.raises(SceneFormatError, match="house"):
        load_scene(str(d))


@pytest.mark.parametrize("opt", ["up=0,0,0", "scale=-1", "scale=1,2", "units_to_meters=0", "units_to_meters=x", "front=nan,0,1"])
def test_bad_frame_options_are_scene_format_errors(tmp_path, opt):
    path = write_glb(tmp_path / "r.glb", _room_y_up())
    with pytest.raises(SceneFormatError):
        load_scene(f"{path}:{opt}")


def test_explicit_stage_config_is_honoured(tmp_path):
    path = write_glb(tmp_path / "r.glb", _room_y_up())
    cfg = tmp_path / "elsewhere" / "mine.stage_config.json"
    cfg.parent.mkdir()
    cfg.write_text(json.dumps({"up": [0, 1, 0], "front": [0, 0, -1], "scale": [2, 2, 2], "units_to_meters": 0.5}))
    lo, hi = load_scene(f"{path}:stage_config={cfg}").bounds_m
    assert hi[0] - lo[0] == pytest.approx(6.0) and hi[2] - lo[2] == pytest.approx(2.0)  # scale 2 x 0.5 m per unit
    with pytest.raises(SceneFormatError, match="does not exist"):
        load_scene(f"{path}:stage_config={tmp_path / 'nope.json'}")


def test_semantic_ply_reader_quads_ascii_and_errors(tmp_path):
    from libs.world.scene_semantics import read_ply_faces

    quad = tmp_path / "q.ply"
    quad.write_text("ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n"
                    "element face 1\nproperty list uchar int vertex_indices\nproperty ushort object_id\nend_header\n"
                    "0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 3 7\n")
    v, t, props = read_ply_faces(quad)
    assert v.shape == (4, 3) and t.tolist() == [[0, 1, 2], [0, 2, 3]] and props["object_id"].tolist() == [7, 7]
    bv, bt = box((0, 0, 0), (1, 1, 1))
    b = write_ply_with_face_ids(tmp_path / "b.ply", bv, bt, object_id=np.arange(12))
    v, t, props = read_ply_faces(b)
    assert np.array_equal(t, bt) and props["object_id"].tolist() == list(range(12))
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b.read_bytes().replace(b"element vertex 8", b"element vertex 5"))
    with pytest.raises(SceneFormatError):
        read_ply_faces(bad)
    (tmp_path / "not.ply").write_text("hello")
    with pytest.raises(SceneFormatError, match="not a PLY"):
        read_ply_faces(tmp_path / "not.ply")


def test_gltf_json_with_external_buffer_and_image(tmp_path):
    """The text flavour of glTF: JSON, an external .bin and an external .png (relative URIs)."""
    import struct as _struct

    tex = np.zeros((4, 4, 3), np.uint8)
    tex[:] = (20, 200, 40)
    v, t = box((0, 0, 0), (1, 1, 1))
    glb = write_glb(tmp_path / "a.glb", [Primitive(v, t, uvs=np.tile([[0.5, 0.5]], (8, 1)), texture=tex)])
    data = glb.read_bytes()
    jlen = _struct.unpack_from("<I", data, 12)[0]
    doc = json.loads(data[20 : 20 + jlen])
    blob = data[20 + jlen + 8 :]
    (tmp_path / "a data.bin").write_bytes(blob)
    doc["buffers"] = [{"byteLength": len(blob), "uri": "a%20data.bin"}]
    view = doc["bufferViews"][doc["images"][0].pop("bufferView")]
    (tmp_path / "tex.png").write_bytes(blob[view["byteOffset"] : view["byteOffset"] + view["byteLength"]])
    doc["images"][0] = {"uri": "tex.png"}
    (tmp_path / "a.gltf").write_text(json.dumps(doc))
    scene = load_scene(str(tmp_path / "a.gltf"))
    assert scene.texture is not None and scene.texture.images[0][0, 0].tolist() == [20, 200, 40]
    assert scene.bounds_m[1] == pytest.approx([1.0, 0.0, 1.0])  # y-up: file z=1 -> world y=-1..0, file y -> world z
    (tmp_path / "tex.png").unlink()
    with pytest.raises(SceneFormatError, match="missing"):
        load_scene(str(tmp_path / "a.gltf"))
