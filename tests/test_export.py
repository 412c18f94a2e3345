"""`fitme export`: the mesh (closed, split at seams, tangent convention, morph targets), the maps (filled,
bit-exact EXR, PNG encodings), the files reloaded by real consumers (trimesh, OpenEXR, the Khronos
glTF-Validator when node and the npm package are there), and bad inputs."""

import json
import struct

import numpy as np
import pytest
from click.testing import CliRunner

from fitme_cli.cli import main

TINY_FIT = ["--preset", "fast", "--iterations", "2", "--render-size", "128", "--threads", "1"]


@pytest.fixture(scope="module")
def avatar(tmp_path_factory, models_root, one_thread):
    from fitme_cli.io.images import write_sample_photo

    d = tmp_path_factory.mktemp("export_fit")
    photo = write_sample_photo("astronaut", d / "astronaut.jpg")
    out = d / "avatar"
    r = CliRunner().invoke(main, ["fit", str(photo), "-o", str(out), *TINY_FIT])
    assert r.exit_code == 0, r.output
    return out


@pytest.fixture(scope="module")
def shape_model(models_root):
    from fitme_cli.shape.model import load_shape_model

    return load_shape_model(models_root)


@pytest.fixture(scope="module")
def exported(avatar, shape_model, tmp_path_factory):
    """All three formats at 512^2 (the code path of 1024/2048, four times cheaper)."""
    from fitme_cli.export.pipeline import ExportSettings, export_avatar

    out = tmp_path_factory.mktemp("export") / "out"
    return export_avatar(avatar, out, ExportSettings(formats=("glb", "gltf", "obj"), resolution=512), shape_model)


def _glb(path):
    data = path.read_bytes()
    magic, version, total = struct.unpack("<III", data[:12])
    assert (magic, version, total) == (0x46546C67, 2, len(data))
    jlen, jtype = struct.unpack("<II", data[12:20])
    assert jtype == 0x4E4F534A and jlen % 4 == 0
    doc = json.loads(data[20:20 + jlen])
    blen, btype = struct.unpack("<II", data[20 + jlen:28 + jlen])
    assert btype == 0x004E4942
    return doc, data[28 + jlen:28 + jlen + blen]


def _accessor(doc, binary, i):
    """Decode accessor i, sparse included (an independent reader of what the writer wrote)."""
    a = doc["accessors"][i]
    ncomp = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}[a["type"]]
    dt = {5126: np.float32, 5125: np.uint32, 5123: np.uint16}[a["componentType"]]

    def view(v, dtype, count, comps):
        bv = doc["bufferViews"][v]
        return np.frombuffer(binary, dtype, count * comps, bv.get("byteOffset", 0)).reshape(count, comps)

    out = view(a["bufferView"], dt, a["count"], ncomp).copy() if "bufferView" in a else np.zeros((a["count"], ncomp), dt)
    if "sparse" in a:
        sp = a["sparse"]
        idt = {5125: np.uint32, 5123: np.uint16, 5121: np.uint8}[sp["indices"]["componentType"]]
        idx = view(sp["indices"]["bufferView"], idt, sp["count"], 1)[:, 0]
        assert (np.diff(idx.astype(np.int64)) > 0).all()  # the spec wants strictly increasing indices
        out[idx] = view(sp["values"]["bufferView"], dt, sp["count"], ncomp)
    return out


# ------------------------------------------------------------------------------------------- mesh


def test_mesh_is_a_closed_outward_head_split_only_at_uv_seams(exported, shape_model):
    import trimesh

    m = exported.mesh
    assert m.n_vertices >= shape_model.mean.shape[0] and len(m.faces) > shape_model.triangles.shape[0]
    # each export vertex is one (position, uv) pair: the same position and uv never appear twice
    pairs = np.concatenate([m.position_index[:, None], np.round(m.uv * 1e6)], 1)
    assert len(np.unique(pairs, axis=0)) == m.n_vertices
    welded = trimesh.Trimesh(m.neutral.positions, m.faces, process=False)
    welded.merge_vertices(merge_tex=True, merge_norm=True)
    assert welded.is_watertight and welded.is_winding_consistent  # eyes and mouth closed
    assert welded.volume > 0.002  # outward, metres^3 (a head is ~4 litres)
    ext = m.neutral.positions.max(0) - m.neutral.positions.min(0)
    assert 0.12 < ext[0] < 0.22 and 0.22 < ext[1] < 0.40  # metres: a head and neck, not millimetres


def test_normals_and_tangents_follow_gltf_conventions(exported):
    m, g = exported.mesh, exported.mesh.neutral
    assert np.allclose(np.linalg.norm(g.normals, axis=1), 1, atol=1e-5)
    assert np.allclose(np.linalg.norm(g.tangents[:, :3], axis=1), 1, atol=1e-5)
    assert set(np.unique(g.tangents[:, 3])) <= {-1.0, 1.0}
    assert np.abs((g.normals * g.tangents[:, :3]).sum(1)).max() < 1e-4
    # per triangle: tangent along +s, bitangent (w * n x t) along +v = -t in glTF's flipped texcoords
    f = m.faces
    p, uv = g.positions.astype(np.float64), m.uv.astype(np.float64)
    e1, e2 = p[f[:, 1]] - p[f[:, 0]], p[f[:, 2]] - p[f[:, 0]]
    d1, d2 = uv[f[:, 1]] - uv[f[:, 0]], uv[f[:, 2]] - uv[f[:, 0]]
    det = d1[:, 0] * d2[:, 1] - d2[:, 0] * d1[:, 1]
    dpdu = (e1 * d2[:, 1:2] - e2 * d1[:, 1:2]) / det[:, None]
    dpdv = (e2 * d1[:, 0:1] - e1 * d2[:, 0:1]) / det[:, None]
    t = g.tangents[f].mean(1)
    b = np.cross(g.normals[f].mean(1), t[:, :3]) * np.sign(t[:, 3:])
    ok = np.abs(det) > 1e-10
    assert ((t[:, :3] * dpdu).sum(1)[ok] > 0).mean() > 0.99  # the rest: lips, crown, neck bottom (UV folds)
    assert ((b * dpdv).sum(1)[ok] > 0).mean() > 0.99


def test_morph_targets_are_the_arkit_expressions(exported, shape_model):
    m = exported.mesh
    assert m.target_names == shape_model.expression_names and len(m.target_names) == 52
    jaw = m.target_names.index("jawOpen")
    d = m.target_positions[jaw]
    assert d[:, 1].min() < -0.005  # the jaw drops by millimetres (in metres)
    moved = np.linalg.norm(d, axis=1) > 0
    assert 0 < moved.sum() < m.n_vertices  # local: sparse accessors pay off
    assert np.isfinite(m.target_normals).all() and (m.weights == 0).all()
    # the lower lip moves down more than the upper lip: a jaw, not a translation of the whole mouth
    lips = (np.abs(m.neutral.positions[:, 0]) < 0.01) & (m.neutral.positions[:, 2] > m.neutral.positions[:, 2].max() - 0.03)
    y = m.neutral.positions[:, 1]
    mouth_y = y[lips & (np.abs(y - np.median(y[lips])) < 0.03)]
    assert mouth_y.size
    assert np.abs(d[:, 1]).max() > 5 * np.abs(d[y > y.max() - 0.05, 1]).max(initial=0.0)  # the crown stays put


# ------------------------------------------------------------------------------------------- maps


def test_push_pull_fills_holes_from_their_surroundings():
    from fitme_cli.export.maps import push_pull_fill

    rng = np.random.default_rng(0)
    img = np.full((64, 64, 3), 0.5, np.float32) + rng.normal(0, 0.01, (64, 64, 3)).astype(np.float32)
    img[:, 32:] += 0.3
    valid = np.ones((64, 64), bool)
    valid[20:30, 10:20] = False  # a hole in the left half
    valid[40:44, 40:60] = False  # and one in the right half
    holed = np.where(valid[..., None], img, 0.0).astype(np.float32)
    out = push_pull_fill(holed, valid)
    assert np.array_equal(out[valid], holed[valid])  # valid texels untouched
    assert np.abs(out[20:30, 10:20] - 0.5).max() < 0.05 and np.abs(out[40:44, 40:60] - 0.8).max() < 0.05
    with pytest.raises(ValueError, match="no valid"):
        push_pull_fill(holed, np.zeros((64, 64), bool))


def test_maps_have_no_black_holes_even_when_the_source_does(exported, avatar, shape_model):
    from fitme_cli.export.maps import MapSettings, SourceMaps, prepare_maps, uv_coverage
    from fitme_cli.export.mesh import head_topology
    from fitme_cli.export.source import load_source

    a = exported.maps
    src = load_source(avatar).maps
    assert np.isfinite(a.albedo).all() and np.isfinite(a.specular).all()
    # the generator draws a few pure-black hair texels itself; a hole would be a whole black block
    lum = a.albedo @ np.array([0.2126, 0.7152, 0.0722], np.float32)
    blocks = lum.reshape(64, 8, 64, 8).max((1, 3))  # 8 x 8 blocks of the 512^2 map
    assert blocks.min() > 0.003
    src_black = ((src.albedo @ np.array([0.2126, 0.7152, 0.0722], np.float32)) < 0.003).mean()
    assert (lum < 0.003).mean() <= 1.5 * src_black + 1e-4  # upsampling adds no black specks (no ringing)
    assert np.allclose(np.linalg.norm(a.normals, axis=-1), 1, atol=1e-3) and a.normals[..., 2].min() > 0
    assert a.coverage.mean() > 0.95  # the layout uses nearly the whole square (u wrapped)
    # a source with black, NaN holes outside the mesh: all gone after the fill
    topo = head_topology(shape_model)
    outside = ~uv_coverage(topo.uv, topo.uv_faces, src.albedo.shape[0])
    assert outside.any()
    bad_albedo = np.where(outside[..., None], 0.0, src.albedo).astype(np.float32)
    bad_albedo[outside.nonzero()[0][0], outside.nonzero()[1][0]] = np.nan
    filled = prepare_maps(SourceMaps(bad_albedo, src.specular, src.normals), topo.uv, topo.uv_faces, MapSettings(256))
    lum = filled.albedo @ np.array([0.2126, 0.7152, 0.0722], np.float32)
    assert np.isfinite(filled.albedo).all() and lum[outside].mean() > 0.02  # black holes filled
    assert filled.filled_fraction > 0


def test_u_seam_is_continuous_after_upsampling(exported):
    import cv2

    a = exported.maps.albedo
    d = a[:, 0] - a[:, -1]  # neighbours on the head, across the back seam
    across = np.abs(d).mean()
    k = 16  # a step between neighbouring columns in the same texture (scalp and neck) on either side
    local = 0.5 * (np.abs(a[:, 1:k] - a[:, : k - 1]).mean() + np.abs(a[:, -k + 1 :] - a[:, -k:-1]).mean())
    # blend_u_seam matches the edges' vertically smoothed colours, not single strands: strands that do not
    # line up across the seam stay (the 151 kimg G's scalp, 2026-11-26: across 1.46x the local step, 3.19x
    # without the blend), while the smoothed difference, what reads as a seam, drops to 0.39x (2.46x without).
    # The old bound, 1.5x the mean step over the whole map (mostly smooth skin), failed on that scalp: 1.63x
    low = cv2.GaussianBlur(d.reshape(d.shape[0], -1), (1, 0), 0, sigmaY=4.0, borderType=cv2.BORDER_REFLECT)
    assert across < 2.0 * local, (across, local)
    assert np.abs(low).mean() < 0.75 * local, (np.abs(low).mean(), local)


def test_exr_maps_read_back_bit_exactly(exported):
    import OpenEXR

    from fitme_cli.export.maps import exr_arrays

    want = exr_arrays(exported.maps)
    for kind in ("albedo", "specular", "normals"):
        with OpenEXR.File(str(exported.files[f"{kind}.exr"])) as f:
            got = np.asarray(f.channels()["RGB"].pixels)
        assert got.dtype == np.float16 and got.shape == (512, 512, 3)
        assert np.array_equal(got.view(np.uint16), want[kind].view(np.uint16)), kind


def test_png_maps_encode_as_documented(exported):
    import cv2

    from fitme_cli.io.maps import linear_to_srgb

    m = exported.maps
    n16 = cv2.imread(str(exported.files["normals.png"]), cv2.IMREAD_UNCHANGED)
    assert n16.dtype == np.uint16 and n16.shape == (512, 512, 3)
    assert np.abs(n16[..., ::-1] / 65535 * 2 - 1 - m.normals).max() < 2.5 / 65535
    alb = cv2.imread(str(exported.files["albedo.png"]))[..., ::-1]
    assert np.abs(alb / 255 - linear_to_srgb(m.albedo)).max() <= 0.5 / 255 + 1e-6
    spec = cv2.imread(str(exported.files["specular.png"]), cv2.IMREAD_UNCHANGED)
    assert spec.shape == (512, 512, 3) and np.abs(spec[..., 0] / 255 - linear_to_srgb(m.specular)).max() <= 0.5 / 255 + 1e-6


# ------------------------------------------------------------------------------------------- files


def test_trimesh_reloads_glb_and_obj_with_the_same_vertices_and_uvs(exported):
    import trimesh

    m = exported.mesh
    scene = trimesh.load(str(exported.files["head.glb"]), process=False)
    (g,) = scene.geometry.values()
    assert g.vertices.shape == (m.n_vertices, 3) and np.array_equal(g.faces, m.faces)
    assert np.allclose(g.vertices, m.neutral.positions, atol=1e-7)
    assert np.allclose(g.visual.uv, m.uv, atol=1e-6)
    assert g.visual.material.baseColorTexture.size == (512, 512)
    obj = trimesh.load(str(exported.files["head.obj"]), process=False, maintain_order=True)
    assert obj.vertices.shape == (m.n_vertices, 3) and np.array_equal(obj.faces, m.faces)
    assert np.allclose(obj.visual.uv, m.uv, atol=1e-6) and np.allclose(obj.vertices, m.neutral.positions, atol=1e-6)
    assert np.allclose(obj.vertex_normals, m.neutral.normals, atol=1e-4)
    assert obj.visual.material.image.size == (512, 512)  # the MTL's map_Kd resolved


def test_glb_holds_material_extension_and_sparse_targets_that_decode_to_the_deltas(exported):
    m = exported.mesh
    doc, binary = _glb(exported.files["head.glb"])
    assert doc["asset"]["version"] == "2.0" and doc["extensionsUsed"] == ["KHR_materials_specular"]
    mat = doc["materials"][0]
    spec = mat["extensions"]["KHR_materials_specular"]
    assert "specularColorTexture" in spec and spec["specularColorFactor"][0] == pytest.approx(6.25, rel=1e-4)
    assert mat["pbrMetallicRoughness"]["metallicFactor"] == 0 and "normalTexture" in mat
    assert doc["samplers"][0]["wrapS"] == 10497  # u wraps at the back seam
    mesh = doc["meshes"][0]
    assert mesh["extras"]["targetNames"] == m.target_names and mesh["weights"] == [0.0] * 52
    prim = mesh["primitives"][0]
    assert set(prim["attributes"]) == {"POSITION", "NORMAL", "TANGENT", "TEXCOORD_0"}
    st = _accessor(doc, binary, prim["attributes"]["TEXCOORD_0"])
    assert np.allclose(st, np.stack([m.uv[:, 0], 1 - m.uv[:, 1]], 1))  # glTF's t = 1 - v
    for i in (m.target_names.index("jawOpen"), m.target_names.index("tongueOut")):
        pos = _accessor(doc, binary, prim["targets"][i]["POSITION"])
        assert np.array_equal(pos, m.target_positions[i])
        assert np.allclose(_accessor(doc, binary, prim["targets"][i]["NORMAL"]), m.target_normals[i])
    assert "sparse" not in doc["accessors"][prim["targets"][m.target_names.index("tongueOut")]["POSITION"]]


def test_gltf_validator_reports_no_errors(exported):
    from fitme_cli.export.validate import find_validator, validate_gltf

    if find_validator() is None:
        pytest.skip("node or the npm package gltf-validator is not installed (make verify-export installs it "
                    "into .cache/npm; so does make test when npm is present)")
    for name in ("head.glb", "head.gltf"):
        rep = validate_gltf(exported.files[name])
        assert rep.errors == 0, (name, rep.messages[:5])
        assert rep.warnings == 0, (name, rep.messages[:5])
        assert rep.raw["info"]["totalVertexCount"] == exported.mesh.n_vertices


def test_fitted_expression_poses_the_obj_and_sets_the_gltf_weights(avatar, shape_model, tmp_path):
    from safetensors.torch import load_file

    from fitme_cli.export.pipeline import ExportSettings, export_avatar

    p_e = load_file(str(avatar / "params.safetensors"))["p_e"][0].numpy()
    r = export_avatar(avatar, tmp_path / "fitted", ExportSettings(formats=("glb", "obj"), maps=("png",), resolution=256,
                                                                 expression="fitted"), shape_model)
    assert r.expression.startswith("fitted")
    doc, _ = _glb(r.files["head.glb"])
    assert np.allclose(doc["meshes"][0]["weights"], p_e, atol=1e-6)
    v = np.array([[float(x) for x in ln.split()[1:]] for ln in r.files["head.obj"].read_text().splitlines() if ln.startswith("v ")])
    m = r.mesh
    assert np.allclose(v, m.posed.positions, atol=1e-6)
    # posing by the weights is the neutral mesh plus the weighted deltas (the model is linear)
    assert np.allclose(m.neutral.positions + np.einsum("e,enc->nc", m.weights, m.target_positions), m.posed.positions, atol=1e-6)
    assert not (r.out_dir / "albedo.exr").exists()  # --maps png only


# ------------------------------------------------------------------------------------------- CLI and bad inputs


def test_cli_export_writes_and_refuses_to_overwrite_without_force(avatar, tmp_path):
    out = tmp_path / "cli"
    args = ["export", str(avatar), "-o", str(out), "--format", "glb", "--resolution", "256", "--maps", "exr", "--threads", "1"]
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 0, r.output
    assert sorted(p.name for p in out.iterdir()) == ["albedo.exr", "export.json", "head.glb", "normals.exr", "specular.exr"]
    rep = json.loads((out / "export.json").read_text())
    assert rep["mesh"]["morph_targets"] == 52 and rep["sizes"]["head.glb"] == (out / "head.glb").stat().st_size
    before = (out / "head.glb").read_bytes()
    (out / "head.glb").write_bytes(b"mine")
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 17 and "already exist" in r.output and "--force" in r.output
    assert (out / "head.glb").read_bytes() == b"mine"  # untouched
    r = CliRunner().invoke(main, args + ["--force"])
    assert r.exit_code == 0, r.output
    assert (out / "head.glb").read_bytes() == before  # deterministic
    assert not [p for p in out.iterdir() if p.name.startswith(".")]  # no staging left behind


@pytest.mark.parametrize("case", ["missing", "not_avatar", "corrupt_json", "corrupt_params", "missing_map"])
def test_cli_export_bad_avatar_directories(avatar, tmp_path, case):
    import shutil

    bad = tmp_path / "bad"
    if case == "not_avatar":
        bad.mkdir()
        (bad / "notes.txt").write_text("hello")
    elif case != "missing":
        shutil.copytree(avatar, bad)
        if case == "corrupt_json":
            (bad / "avatar.json").write_text("{not json")
        elif case == "corrupt_params":
            (bad / "params.safetensors").write_bytes(b"\x00" * 100)
        else:
            (bad / "maps" / "avatar_normals.exr").unlink()
    r = CliRunner().invoke(main, ["export", str(bad), "-o", str(tmp_path / "out"), "--resolution", "256"])
    assert r.exit_code == 23, r.output  # AvatarInvalid
    assert "fitme: error:" in r.output and "Traceback" not in r.output
    assert not (tmp_path / "out").exists()


def test_export_refuses_an_avatar_fitted_under_another_shape_model(avatar, shape_model, tmp_path):
    """A rebuilt basis gives the fitted coefficients another face: refused, not exported silently."""
    import copy
    import shutil

    from safetensors.torch import load_file, save_file

    from fitme_cli.errors import ModelMismatch
    from fitme_cli.export.pipeline import ExportSettings, export_avatar
    from fitme_cli.fitting.avatar import SHAPE_TOLERANCE_MM, check_shape_model, load_avatar

    av = load_avatar(avatar)
    inv = av.inversion
    assert check_shape_model(avatar, inv.p_s, inv.p_e, av.fitted_vertices, shape_model) < 1e-3
    other = copy.deepcopy(shape_model)
    k = int(inv.p_s.abs().argmax())
    other.identity_basis[:, :, k] *= -1  # a sign flip, as an eigensolver on another BLAS may give
    with pytest.raises(ModelMismatch, match="mm away") as e:
        export_avatar(avatar, tmp_path / "out", ExportSettings(resolution=256), other)
    assert e.value.exit_code == 26 and not (tmp_path / "out").exists()
    tiny = copy.deepcopy(shape_model)
    tiny.mean += 0.2 * SHAPE_TOLERANCE_MM  # far above float noise, far below a changed face: passes
    assert 0.3 * SHAPE_TOLERANCE_MM < check_shape_model(avatar, inv.p_s, inv.p_e, av.fitted_vertices, tiny) < SHAPE_TOLERANCE_MM
    # an avatar from before params.fitted_vertices (schema 1.1) is checked against its per-photo OBJs
    old = tmp_path / "old"
    shutil.copytree(avatar, old)
    params = load_file(str(old / "params.safetensors"))
    del params["fitted_vertices"]
    save_file(params, str(old / "params.safetensors"))
    fallback = load_avatar(old).fitted_vertices
    assert (fallback - av.fitted_vertices).abs().max() < 1e-3  # the OBJ keeps 4 decimals of mm
    with pytest.raises(ModelMismatch, match="mm away"):
        check_shape_model(old, inv.p_s, inv.p_e, fallback, other)
    # with neither, nothing to check against: refused with the way out
    shutil.rmtree(old / "photos")
    r = CliRunner().invoke(main, ["export", str(old), "-o", str(tmp_path / "out2"), "--resolution", "256"])
    assert r.exit_code == 26 and "records no fitted mesh" in r.output and "fitme fit" in r.output


def test_cli_export_bad_output_paths(avatar, tmp_path):
    r = CliRunner().invoke(main, ["export", str(avatar), "-o", str(avatar / "export"), "--resolution", "256"])
    assert r.exit_code == 17 and "inside the avatar directory" in r.output
    assert not (avatar / "export").exists()
    blocker = tmp_path / "file"
    blocker.write_text("x")
    r = CliRunner().invoke(main, ["export", str(avatar), "-o", str(blocker / "sub"), "--resolution", "256"])
    assert r.exit_code == 17, r.output  # OutputNotWritable: a file where a directory must be
    r = CliRunner().invoke(main, ["export", str(avatar), "-o", str(blocker), "--resolution", "256"])
    assert r.exit_code == 17 and "not a directory" in r.output
    r = CliRunner().invoke(main, ["export", str(avatar), "-o", str(tmp_path / "o"), "--format", "fbx"])
    assert r.exit_code == 2 and "fbx" in r.output


def test_settings_reject_bad_values():
    from fitme_cli.export.maps import MapSettings
    from fitme_cli.export.pipeline import ExportSettings

    with pytest.raises(ValueError, match="formats"):
        ExportSettings(formats=("glb", "glb"))
    with pytest.raises(ValueError, match="expression"):
        ExportSettings(expression="happy")
    with pytest.raises(ValueError, match="power of two"):
        MapSettings(resolution=1000)
