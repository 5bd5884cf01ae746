"""Large export files as pieces (``scanpipe.artifacts.Pieces``): written and hashed piece by
piece, the same bytes as joined, the chain's export identical to ``scanpipe export``."""

from __future__ import annotations

import hashlib
from collections.abc import Callable, Iterator
from pathlib import Path

import pyarrow as pa
import pytest
from result_tables import points_table, textured_box

from scanpipe.artifacts import (
    Pieces,
    Stream,
    file_bytes,
    file_pieces,
    file_sha256,
    file_size,
    read_artifact,
    write_artifact,
    write_together,
)
from scanpipe.errors import ArtifactError
from scanpipe.exporters import obj, textfmt
from scanpipe.progress import no_progress
from scanpipe.stage import complete_manifest
from scanpipe.stages import export as ex
from scanpipe.stages.export import INPUT_ARTIFACTS, ExportStageParams, export_stage
from scanpipe.workdir import find_artifacts


def _sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def test_pieces_hash_size_and_write_as_the_joined_bytes(tmp_path: Path) -> None:
    import numpy as np

    array = np.arange(1000, dtype=np.float32)
    pieces = Pieces((b"head\n", memoryview(array).cast("B"), b"", b"tail"))
    joined = b"head\n" + array.tobytes() + b"tail"
    assert file_bytes(pieces) == joined
    assert file_size(pieces) == len(joined) == 4009
    assert file_sha256(pieces) == _sha(joined)
    out = tmp_path / "stage"
    write_together(out, "stage", {}, {"big.bin": pieces, "sub/small.txt": b"x"}, True)
    assert (out / "big.bin").read_bytes() == joined
    assert (out / "sub" / "small.txt").read_bytes() == b"x"


def test_a_failed_write_of_pieces_keeps_the_previous_set(tmp_path: Path) -> None:
    out = tmp_path / "flat"
    out.mkdir()
    (out / "a.obj").write_bytes(b"old a")
    (out / "b.glb").mkdir()  # a folder where a file of the set must go
    with pytest.raises(ArtifactError, match=r"b\.glb: is a folder"):
        write_together(out, "export", {}, {"a.obj": Pieces((b"new ", b"a")), "b.glb": b"b"},
                       False)
    assert (out / "a.obj").read_bytes() == b"old a"
    assert sorted(p.name for p in out.iterdir()) == ["a.obj", "b.glb"]


@pytest.fixture
def workdir(tmp_path: Path) -> Path:
    """Artifacts of a textured box and a cloud, as a run leaves them (provenance and all)."""
    root = tmp_path / "work"
    box = textured_box()
    for stage, tables in (("filter", {"points": points_table(profiles=5, seed=3)}),
                          ("mesh", {k: box[k] for k in ("mesh_vertices", "mesh_faces")}),
                          ("texture", {k: box[k] for k in ("textured_faces",
                                                            "texture_pages")})):
        for name, table in tables.items():
            write_artifact(root / stage / f"{name}.parquet", table,
                           {"stage": stage, "key": f"{stage}-key", "rows": table.num_rows})
    return root


def test_chain_export_equals_scanpipe_export_and_its_manifest(
        cli: Callable, workdir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The stage's files, written by ``write_together`` piece by piece (many pieces: tiny
    slices and blocks; the OBJ streamed), are byte for byte ``scanpipe export``'s; the
    manifest made while writing has the written files' sizes and digests, as the in-memory
    one (``Stage.call``) has."""
    monkeypatch.setattr(obj, "FACE_SLICE", 3)
    monkeypatch.setattr(textfmt, "BLOCK_ROWS", 2)
    tables: dict[str, pa.Table] = {
        name: read_artifact(path)[0]
        for name, path in find_artifacts(workdir, INPUT_ARTIFACTS).items()}
    result = export_stage(tables, ExportStageParams(), no_progress)
    streamed = result.files["model.obj"]
    assert isinstance(streamed, Stream)
    assert len(list(file_pieces(streamed))) > 4
    assert "export_manifest" not in result.tables and result.manifest == "export_manifest"
    stage_dir = tmp_path / "run" / "export"
    manifest = write_together(stage_dir, "export", {}, result.files, True,
                              ("export_manifest", {"stage": "export"}))
    assert manifest is not None
    assert read_artifact(stage_dir / "export_manifest.parquet")[0].equals(manifest)
    written = {row["file"]: (stage_dir / row["file"]).read_bytes()
               for row in manifest.to_pylist()}
    assert set(written) == set(result.files)
    for row in manifest.to_pylist():
        assert row["bytes"] == len(written[row["file"]])
        assert row["sha256"] == _sha(written[row["file"]])
    in_memory = export_stage(tables, ExportStageParams(), no_progress)
    complete_manifest(in_memory)  # what Stage.call does when nothing is written
    assert in_memory.tables["export_manifest"].equals(manifest)

    out = tmp_path / "cli"
    for fmt in ("obj", "glb"):
        run = cli("export", workdir, "--format", fmt, "--out", out / f"model.{fmt}")
        assert run.code == 0, run.err
    exported = {p.name: p.read_bytes() for p in out.iterdir()}
    mesh_files = {k: v for k, v in written.items() if k.startswith("model")}
    assert exported == mesh_files


def test_a_stream_is_made_block_by_block_and_a_failing_one_keeps_the_previous_set(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The OBJ's text comes one block at a time (never the whole text at once); a stream
    that fails part-way leaves the stage's previous files and no staging behind."""
    monkeypatch.setattr(textfmt, "BLOCK_ROWS", 4)
    box = textured_box()
    mesh = ex.models_from_tables({k: box[k] for k in (*ex.MESH_ARTIFACTS,
                                                       *ex.TEXTURE_ARTIFACTS)})[0]
    assert mesh is not None
    streamed = obj.obj_files(mesh, "model")["model.obj"]
    assert isinstance(streamed, Stream)
    pieces = [bytes(p) for p in file_pieces(streamed)]
    whole = b"".join(pieces)
    assert max(len(p) for p in pieces) < len(whole) // 4
    assert file_bytes(streamed) == whole  # made afresh, the same bytes

    out = tmp_path / "run" / "export"
    write_together(out, "export", {}, {"model.obj": b"old"}, True)

    def broken() -> Iterator[bytes]:
        yield b"v 0 0 0\n"
        raise ArtifactError("mesh_faces: cannot be read")

    with pytest.raises(ArtifactError, match="cannot be read"):
        write_together(out, "export", {}, {"model.obj": Stream(broken)}, True,
                       ("export_manifest", {"stage": "export"}))
    assert (out / "model.obj").read_bytes() == b"old"
    assert sorted(p.name for p in out.iterdir()) == ["model.obj"]
    assert not any((tmp_path / "run" / ".scanpipe").glob("tmp-*"))


def test_pieces_are_written_and_hashed_in_order_beside_their_making(tmp_path: Path) -> None:
    """A file of many pieces is written on one thread and hashed on another while the next
    pieces are made: the bytes and digest of the joined pieces, in order; a write that fails
    part-way raises its OSError once the pieces in flight are done, and nothing after it is
    made."""
    import numpy as np

    from scanpipe.artifacts import PIECES_IN_FLIGHT, write_file_data

    rng = np.random.default_rng(5)
    parts = [rng.integers(0, 256, int(n), np.uint8).tobytes()
             for n in rng.integers(0, 50_000, 200)]
    made: list[int] = []

    def make() -> Iterator[bytes]:
        for index, part in enumerate(parts):
            made.append(index)
            yield part

    joined = b"".join(parts)
    path = tmp_path / "big.bin"
    with path.open("wb") as handle:
        digest = write_file_data(handle, Stream(make), hashed=True)
    assert path.read_bytes() == joined
    assert digest.nbytes == len(joined) and digest.sha256 == _sha(joined)
    assert write_file_data(tmp_path.joinpath("b").open("wb"), Pieces(tuple(parts))).sha256 == ""

    class Full:
        """A disk that fills up at the fifth piece."""

        def __init__(self) -> None:
            self.written: list[bytes] = []

        def write(self, part: bytes) -> int:
            if len(self.written) == 4:
                raise OSError(28, "No space left on device")
            self.written.append(bytes(part))
            return len(part)

    made.clear()
    full = Full()
    with pytest.raises(OSError, match="No space left"):
        write_file_data(full, Stream(make), hashed=True)  # type: ignore[arg-type]
    assert full.written == parts[:4]
    assert len(made) <= 5 + PIECES_IN_FLIGHT + 1
