"""Texture quality on the virtual rig: simulate → decode → texture (truth geometry) → render.

The mesh is the truth scene's own geometry, finely subdivided, so that the figure measures the
texture alone (the mesh stage has its own accuracy tests).
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np
import pyarrow as pa
import pytest
import trimesh

from scanpipe.artifacts import read_artifact
from scanpipe.camera import camera_pose_in_rig
from scanpipe.evaluate import load_reference, texture_psnr
from scanpipe.motion import beta_deg_at
from scanpipe.pipeline import execute, registry, run_chain, validate_pipeline_params
from scanpipe.render import RenderMesh
from scanpipe.rig import rig_from_table
from scanpipe.sim.direct import simulate_direct
from scanpipe.sim.options import SimOptions
from scanpipe.sim.truth import load_truth

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def simulated(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    folder = tmp_path_factory.mktemp("sim")
    options = SimOptions(motor_step_deg=6.0, beam_step_deg=4.0, camera_scale=0.125,
                         camera_fps=2.0)
    simulate_direct(folder / "scan.mcap", folder / "truth", options)
    stage = registry()["decode"]
    record = execute(stage, {"recording": folder / "scan.mcap"}, folder / "decode",
                     stage.params())
    truth = load_truth(folder / "truth")
    vertices, faces = trimesh.remesh.subdivide_to_size(
        np.asarray(truth.scene.vertices), np.asarray(truth.scene.triangles), max_edge=0.15)
    normals = np.array(trimesh.Trimesh(vertices, faces, process=False).vertex_normals)
    normals[np.einsum("ij,ij->i", normals, -vertices) < 0] *= -1  # towards the scanner
    inputs = {name: read_artifact(record.outputs[name])[0] for name in ("frames", "motor", "rig")}
    inputs["mesh_vertices"] = pa.table(
        {**{c: pa.array(vertices[:, k].astype(np.float32)) for k, c in enumerate("xyz")},
         **{c: pa.array(normals[:, k].astype(np.float32)) for k, c in enumerate(("nx", "ny",
                                                                               "nz"))}})
    inputs["mesh_faces"] = pa.table({c: pa.array(faces[:, k].astype(np.int32))
                                     for k, c in enumerate(("v0", "v1", "v2"))})
    return {"inputs": inputs, "vertices": vertices, "faces": faces, "truth": truth,
            "reference": load_reference(folder / "truth"), "folder": folder}


def render_mesh(tables: dict[str, pa.Table], vertices: np.ndarray, faces: np.ndarray
                ) -> RenderMesh:
    tf = tables["textured_faces"]
    uv = np.stack([np.stack([tf.column(f"u{k}").to_numpy(), tf.column(f"v{k}").to_numpy()], 1)
                   for k in range(3)], 1)
    pages = {i: cv2.cvtColor(cv2.imdecode(np.frombuffer(p.as_py(), np.uint8), 1),
                             cv2.COLOR_BGR2RGB)
             for i, p in enumerate(tables["texture_pages"].column("png"))}
    return RenderMesh(vertices.astype(np.float32), faces.astype(np.int32),
                      face_uvs=uv.astype(np.float32),
                      face_pages=tf.column("page").to_numpy().astype(np.int32), pages=pages)


def occluded_faces(tables: dict[str, pa.Table], sim: dict[str, Any]) -> int:
    """Textured faces with any of 16 interior points hidden (against the TRUTH scene) from the
    camera centre of the frame they were textured from."""
    frames, motor = sim["inputs"]["frames"], sim["inputs"]["motor"]
    rig = rig_from_table(sim["inputs"]["rig"])
    beta = beta_deg_at(frames.column("log_time_ns").to_numpy(), motor, rig.motor)
    where = {(c, s): b for c, s, b in zip(frames.column("camera_id").to_pylist(),
                                          frames.column("sequence").to_pylist(), beta,
                                          strict=True)}
    tf = tables["textured_faces"]
    textured = np.flatnonzero(tf.column("page").to_numpy() >= 0)
    cams = tf.column("camera_id").to_pylist()
    seqs = tf.column("frame").to_pylist()
    centres = np.stack([camera_pose_in_rig(rig.camera(cams[f]), float(where[(cams[f],
                                                                               seqs[f])]))[1]
                        for f in textured])
    # 16 random interior points, not the ones the stage tests
    bary = np.random.default_rng(11).dirichlet((1.5, 1.5, 1.5), size=16) * 0.94 + 0.02
    corners = sim["vertices"][sim["faces"][textured]]
    points = np.einsum("bk,fkc->fbc", bary, corners).reshape(-1, 3)
    origins = np.repeat(centres, len(bary), axis=0)
    delta = points - origins
    distance = np.linalg.norm(delta, axis=1)
    hits = sim["truth"].scene.cast(origins, delta / distance[:, None])
    hidden = (np.asarray(hits.t_hit_m) < distance - 0.02).reshape(-1, len(bary)).any(axis=1)
    return int(hidden.sum())


@pytest.mark.parametrize("method", ["projective", "panorama"])
def test_texture_psnr_on_the_virtual_rig(simulated: dict[str, Any], method: str) -> None:
    stage = registry()["texture"]
    result = stage.run(simulated["inputs"], method=method)
    assert result.report["coverage"] > 0.2
    mesh = render_mesh(result.tables, simulated["vertices"], simulated["faces"])
    figures = texture_psnr(mesh, simulated["reference"], views=8, width=160)
    assert figures["texture_views"] == 8 and figures["texture_pixels"] > 50_000
    assert figures["texture_psnr_db"] >= 24.0, figures
    assert occluded_faces(result.tables, simulated) == 0


def test_whole_chain_texture_psnr(simulated: dict[str, Any]) -> None:
    """decode → assemble → filter → mesh (Poisson) → texture, rendered against the truth."""
    folder = simulated["folder"]
    records = run_chain(folder / "scan.mcap", folder / "w",
                        validate_pipeline_params(list(registry().values()), {}), to="texture")
    assert [r.stage for r in records][-2:] == ["mesh", "texture"]
    w = folder / "w"
    vt = read_artifact(w / "mesh" / "mesh_vertices.parquet")[0]
    ft = read_artifact(w / "mesh" / "mesh_faces.parquet")[0]
    vertices = np.stack([vt.column(c).to_numpy() for c in "xyz"], 1)
    faces = np.stack([ft.column(c).to_numpy() for c in ("v0", "v1", "v2")], 1)
    tables = {name: read_artifact(w / "texture" / f"{name}.parquet")[0]
              for name in ("textured_faces", "texture_pages")}
    figures = texture_psnr(render_mesh(tables, vertices, faces), simulated["reference"],
                           views=8, width=160)
    assert figures["texture_psnr_db"] >= 24.0, figures


def test_every_progress_bar_finishes(simulated: dict[str, Any]) -> None:
    """The texture stage's bars (frame rating, atlas …) each end at their total."""
    last: dict[str, tuple[float, float | None]] = {}

    def record(task: str, done: float, total: float | None = None) -> None:
        last[task] = (done, total)

    registry()["texture"].run(simulated["inputs"], progress=record)
    assert {"rate frames", "atlas"} <= set(last)
    unfinished = {task: v for task, v in last.items() if v[1] is not None and v[0] != v[1]}
    assert unfinished == {}
