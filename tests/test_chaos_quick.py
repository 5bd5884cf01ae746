"""The chaos suite in quick mode (``python -m benchmarks.chaos --quick``): every attack runs and
every target holds — no tracebacks, every intact scanner frame recovered and no false one, at
most ~1 s of profiles lost per flipped byte, cut or kill, the platform within its limit, bounded
memory on hostile images and headers, no input overwritten, no failed or mixed concurrent run.
The figures and their meaning: docs/reliability.md."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository: `benchmarks`

from benchmarks import chaos, harness


@pytest.fixture(scope="module")
def results(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    figures = chaos.run_suite(quick=True, seed=0)
    saved = harness.save(figures, "chaos-quick", results_dir=tmp_path_factory.mktemp("chaos"))
    loaded: dict[str, Any] = json.loads(saved.read_text())
    loaded["_report"] = chaos.report(figures)
    return loaded


def _missed(results: dict[str, Any], attack: str) -> list[str]:
    """The targets of ``attack`` that were missed, with the first findings as reproducers."""
    missed = [f"{t['figure']} = {t['value']} (target {t['target']})"
              for t in results["targets"] if t["attack"] == attack and not t["ok"]]
    if missed:
        missed += [f"{f['what']}: {f['reproducer'][:300]}\n{f['detail'][:1500]}"
                   for f in results["findings"] if f["attack"] == attack][:3]
    return missed


@pytest.mark.slow
def test_every_attack_ran_and_reported_its_targets(results: dict[str, Any]) -> None:
    assert list(results["attacks"]) == list(chaos.ATTACKS)
    attacked = {t["attack"] for t in results["targets"]}
    assert attacked == set(chaos.ATTACKS)
    assert all("error" not in figures for figures in results["attacks"].values()), \
        results["_report"]
    assert "attack" in results["_report"] and results["machine"]["cpus"] >= 1
    streams = results["attacks"]["streams"]
    assert streams["cases"] >= 300 and streams["intact_frames"] > 1000
    assert results["attacks"]["recordings"]["profiles"] > 100
    assert results["attacks"]["kills"]["files_on_disk"] >= 1


@pytest.mark.slow
@pytest.mark.parametrize("attack", list(chaos.ATTACKS))
def test_targets_hold(results: dict[str, Any], attack: str) -> None:
    assert _missed(results, attack) == []
