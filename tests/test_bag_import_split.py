"""``import-bag`` on one part of a split recording (``rosbag record --split``: NAME_0.bag,
NAME_1.bag …; rosbag2's NAME_0.mcap … in its folder). Given the first part, only its share of
the scan was imported, without a word."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rosbags.rosbag1 import Writer as Writer1
from rosbags.typesys import Stores, get_typestore
from test_bag_import import (
    DEFAULT_R_PL,
    PROFILES,
    SCAN_TIME,
    T0,
    assembled,
    check_against_truth,
    ros_scan,
    turntable_messages,
)


def write_parts(folder: Path, names: list[str], shift_s: list[float],
                cut_s: float = PROFILES * SCAN_TIME / 2) -> list[Path]:
    """The turntable scan split at ``cut_s`` into ROS 1 bags ``names`` (the second part's
    times shifted by ``shift_s[1]``: a gap that says it is another recording)."""
    ts = get_typestore(Stores.ROS1_NOETIC)
    messages = turntable_messages(ts, "joint")
    paths = []
    for k, name in enumerate(names):
        path = folder / name
        with Writer1(path) as writer:
            conns: dict[str, Any] = {}
            for topic, msgtype, t, msg in messages:
                if (t < cut_s) != (k == 0):
                    continue
                if topic not in conns:
                    conns[topic] = writer.add_connection(topic, msgtype, typestore=ts)
                writer.write(conns[topic], T0 + round((t + shift_s[k]) * 1e9) + 1000,
                             ts.serialize_ros1(msg, msgtype))
        paths.append(path)
    return paths


@pytest.mark.parametrize("given", [0, 1])
def test_a_part_is_read_with_the_parts_that_continue_it(tmp_path: Path, cli: Any,
                                                        given: int) -> None:
    parts = write_parts(tmp_path, ["scan_0.bag", "scan_1.bag"], [0.0, 0.0])
    out = tmp_path / "rec.mcap"
    result = cli("import-bag", parts[given], "--out", out)
    assert result.code == 0, result.err
    assert f"{PROFILES} profiles × 541 samples" in result.out
    assert f"scan_{given}.bag: one part of a split recording: read with its parts " \
           "scan_0.bag, scan_1.bag" in result.err
    result = cli("run", out, "--workdir", tmp_path / "w", "--to", "assemble", "-q")
    assert result.code == 0, result.err
    _, truth, _ = ros_scan(DEFAULT_R_PL, np.zeros(3), 0.0)
    check_against_truth(assembled(tmp_path / "w"), truth)


def test_files_named_like_parts_that_do_not_continue_are_read_alone(
        tmp_path: Path, cli: Any) -> None:
    """Two scans a user named scan_0.bag and scan_1.bag, a minute apart: not one recording."""
    parts = write_parts(tmp_path, ["scan_0.bag", "scan_1.bag"], [0.0, 60.0])
    out = tmp_path / "rec.mcap"
    result = cli("import-bag", parts[0], "--out", out)
    assert result.code == 0, result.err
    assert f"{PROFILES // 2} profiles" in result.out
    assert "scan_0.bag: files named like parts of a split recording lie beside it " \
           "(scan_1.bag), but their times do not continue it: read alone" in result.err


def test_an_unclosed_next_part_is_named(tmp_path: Path, cli: Any) -> None:
    """rosbag record killed mid-scan leaves its last part as NAME_1.bag.active (no index)."""
    parts = write_parts(tmp_path, ["scan_0.bag", "scan_1.bag"], [0.0, 0.0])
    parts[1].rename(tmp_path / "scan_1.bag.active")
    result = cli("import-bag", parts[0], "--out", tmp_path / "rec.mcap")
    assert result.code == 0, result.err
    assert "scan_1.bag.active: the next part, left unclosed by its recorder (no index), is " \
           "not read: run `rosbag reindex` on it" in result.err


def test_out_naming_another_part_is_refused(tmp_path: Path, cli: Any) -> None:
    """A rosbag2 split bag's parts are .mcap files: --out must not name one, even with
    --force (the part is read as an input)."""
    from rosbags.rosbag2 import StoragePlugin
    from rosbags.rosbag2 import Writer as Writer2

    ts = get_typestore(Stores.ROS2_HUMBLE)
    messages = turntable_messages(ts, "joint")
    folder = tmp_path / "bag"
    folder.mkdir()
    for k in range(2):
        with Writer2(tmp_path / f"w{k}", version=9, storage_plugin=StoragePlugin.MCAP) as w:
            conns: dict[str, Any] = {}
            for topic, msgtype, t, msg in messages:
                if (t < PROFILES * SCAN_TIME / 2) != (k == 0):
                    continue
                if topic not in conns:
                    conns[topic] = w.add_connection(topic, msgtype, typestore=ts)
                w.write(conns[topic], T0 + round(t * 1e9) + 1000, ts.serialize_cdr(msg, msgtype))
        (tmp_path / f"w{k}" / f"w{k}.mcap").rename(folder / f"bag_{k}.mcap")
    before = (folder / "bag_1.mcap").read_bytes()
    result = cli("import-bag", folder / "bag_0.mcap", "--out", folder / "bag_1.mcap", "--force")
    assert result.code == 2, result.err
    assert "is a file of the bag being imported" in result.err
    assert (folder / "bag_1.mcap").read_bytes() == before
    ok = cli("import-bag", folder / "bag_0.mcap", "--out", tmp_path / "rec.mcap")
    assert ok.code == 0, ok.err
    assert f"{PROFILES} profiles" in ok.out and "read with its parts bag_0.mcap, bag_1.mcap" \
        in ok.err
