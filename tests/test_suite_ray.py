"""The suite solve on Ray: a local Ray instance (``ray.init()`` on this machine), skipped only without Ray."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

ray = pytest.importorskip("ray")

from mpc.benchmark.suite import entry_key, solve_suite  # noqa: E402
from wl_env.suites import load_suite  # noqa: E402

TESTS = str(Path(__file__).resolve().parent)


def test_the_suite_solves_on_a_local_ray_instance_with_the_local_layout(tmp_path, monkeypatch):
    # Ray's workers import the job by name: they find this folder's fakes on PYTHONPATH.
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([TESTS, os.environ.get("PYTHONPATH", "")]))
    r = solve_suite("corners", cache=tmp_path, ray_address="local", limit=3, ray_chunk=2, job="fakes:fake_front_job")
    assert r.solved == 6 and len(r.entries) == 6
    corners = load_suite("corners")
    for b in ("service", "tc"):
        for s in corners.of(b):
            key = entry_key(s)
            if key in r.entries:
                e = r.entries[key]
                assert e["scenario"] == s.to_dict() and e["T_min"] == pytest.approx(4 + 0.5 * (s.reverse_distance + s.forward_distance))
    assert {e["pid"] for e in r.entries.values()} - {os.getpid()}  # solved in Ray's workers, not here
    parts = sorted((tmp_path / "suites").glob("corners_*/*.json"))  # the same layout as the local processes'
    assert len(parts) == 6
    assert json.loads(r.file.read_text())["entries"].keys() == r.entries.keys()
    again = solve_suite("corners", cache=tmp_path, ray_address="local", limit=3, job="fakes:fake_front_job")
    assert again.solved == 0  # resumed: every entry on disk


def test_an_unreachable_ray_address_fails_at_once_by_name():
    """Ray itself retries an unreachable head for minutes, deaf to Ctrl-C (measured: still running after 170 s)."""
    import time

    from mpc.workers import check_reachable

    t0 = time.perf_counter()
    with pytest.raises(ConnectionError, match="--ray 127.0.0.1:1: no Ray head answers there"):
        check_reachable("127.0.0.1:1")
    with pytest.raises(ConnectionError, match="ray://127.0.0.1:1"):
        check_reachable("ray://127.0.0.1:1")
    assert time.perf_counter() - t0 < 12.0
    check_reachable("local")  # (left to Ray)
