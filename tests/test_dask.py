"""Batch evaluation on a real Dask distributed cluster (torchheat.executors, torchheat.batch).

One LocalCluster (2 worker processes of one thread each) serves the module: records equal to
the in-process run with one eigensolve per shape (Dask transfers and the shared disk cache),
a worker killed mid-task, the client killed and restarted, a worker that cannot see the data,
an unreachable scheduler, pairs that raise. Every wait is bounded (``deadline``).
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import sys
import time
from pathlib import Path

import pytest
import yaml
from conftest import ROOT, SHARED, deformed_spheres, kill_after_first_record

distributed = pytest.importorskip("distributed")

from torchheat import batch  # noqa: E402
from torchheat.executors import DaskExecutor, ExecutorError, parse_dask_address  # noqa: E402

N_SHAPES = 4


@contextlib.contextmanager
def deadline(seconds: int):
    """Fail the test (instead of hanging CI) if the block runs longer than ``seconds``."""

    def fire(signum, frame):
        raise TimeoutError(f"test exceeded its {seconds} s deadline")

    old = signal.signal(signal.SIGALRM, fire)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


def _config(tmp: Path, meshes: Path, out: Path, pairs=None, **over) -> Path:
    names = [f"blob{i}" for i in range(N_SHAPES)]
    cfg = {
        "name": out.name, "output": str(out), "dataset": "folder",
        "dataset_args": {"path": str(meshes), "classes": ["blob"] * len(names), "gt": "identity",
                         "pairs": pairs or [[a, b] for a in names for b in names if a != b]},
        "task": "match", "match": {"method": "paper"}, "prepare": {"k": 30},
        "pictures": 0,
    }
    cfg.update(over)
    path = tmp / f"{out.name}.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


def _lines(out: Path) -> list[dict]:
    return [json.loads(s) for s in (out / "results.jsonl").read_text().splitlines()]


def _numbers(recs) -> dict[str, tuple]:
    return {r["name"]: (r["direct"], r["landmarks"], r["curve"], r["n_eval"]) for r in recs}


def _solves(recs) -> tuple[int, int]:
    """(eigensolves in shape tasks, distinct shape-task results), from the records."""
    metas = {m["id"]: m for r in recs for m in r.get("shapes", ())}
    return sum(m["computed"] for m in metas.values()), len(metas)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("dask")
    meshes = tmp / "meshes"
    deformed_spheres(meshes, n=N_SHAPES)  # 642 vertices each: ~0.3 s a pair
    ref_out = tmp / "ref"
    with deadline(120):
        ref = batch.run(_config(tmp, meshes, ref_out), progress=False)  # in-process
    assert len(ref) == N_SHAPES * (N_SHAPES - 1)
    return tmp, meshes, ref


@pytest.fixture(scope="module")
def cluster():
    with deadline(120):
        ex = DaskExecutor("local:2")
    yield ex
    with deadline(60):
        ex.close()


def test_records_equal_in_process_run_with_one_eigensolve_per_shape(data, cluster):
    tmp, meshes, ref = data
    with deadline(180):
        got = batch.run(_config(tmp, meshes, tmp / "mem"), executor=cluster, progress=False)
        # the same through the shared disk cache instead of Dask's transfers
        cached = batch.run(_config(tmp, meshes, tmp / "disk", cache=str(tmp / "cache")),
                           executor=cluster, progress=False)
    for recs, out in ((got, tmp / "mem"), (cached, tmp / "disk")):
        assert _numbers(recs) == _numbers(ref)
        lines = _lines(out)
        assert sorted(r["name"] for r in lines) == sorted(r["name"] for r in ref)
        assert all(r["eigensolves"] == 0 for r in lines)  # none in the pair tasks
        assert _solves(lines) == (N_SHAPES, N_SHAPES)  # one per shape, each once
        assert all(len(r["shapes"]) == 2 for r in lines)
        # each shape task's seconds are shared out over its pairs' preparation times
        metas = {m["id"]: m for r in lines for m in r["shapes"]}
        assert sum(r["time_shapes"] for r in lines) == pytest.approx(
            sum(m["seconds"] for m in metas.values()))
        assert all(r["time_prepare"] >= r["time_shapes"] > 0 for r in lines)
    assert len(list((tmp / "cache").glob("*.npz"))) == N_SHAPES
    assert sum(r["eigensolves"] for r in ref) >= N_SHAPES  # in-process: solved in the pairs
    # a re-run through the cache: shape tasks find their entries, no eigensolve at all
    with deadline(120):
        again = batch.run(_config(tmp, meshes, tmp / "disk2", cache=str(tmp / "cache")),
                          executor=cluster, progress=False)
    assert _solves(again) == (0, N_SHAPES) and _numbers(again) == _numbers(ref)


def test_worker_killed_mid_task_every_pair_exactly_once(data, cluster, tmp_path):
    tmp, meshes, ref = data
    marker = tmp_path / "killed"

    class KillOnce(distributed.WorkerPlugin):
        """Kills its worker process the first time a pair task starts executing there."""

        name = "kill-once"

        def transition(self, key, start, finish, **kw):
            if finish == "executing" and str(key).startswith("pair-"):
                try:
                    fd = os.open(marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
                except FileExistsError:
                    return
                os.write(fd, f"{os.getpid()} {key}".encode())
                os.close(fd)
                os.kill(os.getpid(), signal.SIGKILL)

    pids = set(cluster.client.run(os.getpid).values())
    cluster.client.register_plugin(KillOnce())
    try:
        with deadline(240):
            got = batch.run(_config(tmp, meshes, tmp_path / "out"), executor=cluster,
                            progress=False)
    finally:
        cluster.client.unregister_worker_plugin("kill-once")
    killed_pid, killed_key = marker.read_text().split()
    assert int(killed_pid) in pids
    lines = _lines(tmp_path / "out")
    names = [r["name"] for r in lines]
    assert len(names) == len(set(names)) == len(ref)  # every pair exactly once
    assert _numbers(got) == _numbers(lines) == _numbers(ref)
    # the pair whose worker died was run again, by another process
    (again,) = [r for r in lines if killed_key.startswith(f"pair-{r['name']}-")]
    assert int(again["host"].rsplit(":", 1)[1]) != int(killed_pid)
    solved, distinct = _solves(lines)
    assert N_SHAPES <= solved <= 2 * N_SHAPES  # lost shapes recomputed, still O(shapes)
    with deadline(60):
        cluster.client.wait_for_workers(2)  # the nanny restarted it


def test_client_killed_then_resumed(data, cluster, tmp_path):
    tmp, meshes, ref = data
    out = tmp_path / "out"
    cfg = _config(tmp, meshes, out)
    address = cluster.client.scheduler.address  # an existing scheduler, as on a cluster
    n_before = kill_after_first_record(
        [sys.executable, "-m", "torchheat.cli", "evaluate", str(cfg), "--dask", address,
         "--no-progress"], out / "results.jsonl",
        env=dict(os.environ, PYTHONPATH=str(ROOT)), timeout=120)
    assert 1 <= n_before < len(ref)
    with deadline(180):
        resumed = batch.run(cfg, executor=cluster, progress=False)
    lines = _lines(out)
    names = [r["name"] for r in lines]
    assert len(names) == len(set(names)) == len(ref)
    assert _numbers(lines) == _numbers(resumed) == _numbers(ref)


def test_pairs_that_raise_become_error_records(data, cluster, tmp_path, capsys):
    tmp, meshes, ref = data
    bad = tmp_path / "meshes"
    bad.mkdir()
    for f in meshes.iterdir():
        (bad / f.name).symlink_to(f)
    (bad / "blob9.off").write_text("OFF\n3 1 0\n0 0 0\n1 0 0\n")  # truncated: unreadable
    deformed_spheres(tmp_path / "small", n=1, subdivisions=2)  # 162 vertices
    (bad / "small.off").symlink_to(tmp_path / "small" / "blob0.off")
    pairs = [["blob0", "blob1"], ["blob0", "small"], ["blob9", "blob1"], ["blob1", "blob0"]]
    cfg = _config(tmp, bad, tmp_path / "out", pairs=pairs)
    raw = yaml.safe_load(cfg.read_text())
    raw["dataset_args"]["classes"] = ["blob"] * 5 + ["small"]  # blob0-3, blob9, small
    cfg.write_text(yaml.safe_dump(raw))
    with deadline(120):
        rc = batch.main([str(cfg), "--dask", cluster.client.scheduler.address,
                         "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 1  # some pairs failed
    assert "blob0-small: failed: ValueError: identity ground truth needs equal vertex" in err
    assert "blob9-blob1: failed: RuntimeError: preprocessing blob9 failed:" in err
    assert "blob9.off" in err and "2 of 4 pairs failed (re-run to retry)" in err
    lines = _lines(tmp_path / "out")
    assert sorted(r["name"] for r in lines) == ["blob0-blob1", "blob1-blob0"]
    assert _numbers(lines) == {k: v for k, v in _numbers(ref).items()
                               if k in ("blob0-blob1", "blob1-blob0")}


@pytest.mark.skipif(not (SHARED / "tosca_remeshed_5k").is_dir(), reason="no shared data")
def test_worker_without_the_data_folder_is_named(cluster, tmp_path, monkeypatch):
    monkeypatch.setenv("TORCHHEAT_DATA", str(SHARED))  # the client sees the data
    cfg = {"name": "nodata", "output": str(tmp_path / "out"), "dataset": "tosca_remeshed_5k",
           "dataset_args": {"classes": ["wolf"]}, "match": {"method": "paper"}, "pictures": 0}
    workers = sorted(cluster.workers)

    def setenv(value):  # pickled by value: runs on the worker, sets the worker's environment
        os.environ["TORCHHEAT_DATA"] = value

    cluster.client.run(setenv, str(tmp_path / "nowhere"), workers=workers[:1])
    try:
        with deadline(60), pytest.raises(ExecutorError) as exc:
            batch.run(cfg, executor=cluster, progress=False)
    finally:
        cluster.client.run(setenv, str(SHARED), workers=workers[:1])
    msg = str(exc.value)
    assert f"1 of 2 Dask workers cannot take part: {workers[0]}" in msg
    assert f"dataset folder {tmp_path / 'nowhere'} not found" in msg
    assert not (tmp_path / "out" / "results.jsonl").exists()


def test_unreachable_scheduler_and_bad_addresses(data, capsys):
    tmp, meshes, _ = data
    import dask

    t0 = time.monotonic()
    with deadline(60), dask.config.set({"distributed.comm.timeouts.connect": "2s"}):
        with pytest.raises(ExecutorError, match=r"cannot reach a Dask scheduler at "
                                                r"tcp://127\.0\.0\.1:9 within 2 s"):
            DaskExecutor("127.0.0.1:9")
        cfg = _config(tmp, meshes, tmp / "unreachable")
        assert batch.main([str(cfg), "--dask", "tcp://127.0.0.1:9", "--no-progress"]) == 2
    assert time.monotonic() - t0 < 30
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: cannot reach a Dask scheduler") and "\n" not in err
    assert not (tmp / "unreachable" / "results.jsonl").exists()
    assert batch.main([str(cfg), "--dask", "local:0"]) == 2
    assert batch.main([str(cfg), "--dask", "nonsense"]) == 2
    assert batch.main([str(cfg), "--dask", "local:2", "--workers", "2"]) == 2
    assert "not both" in capsys.readouterr().err
    assert parse_dask_address("local:3") == ("local", 3)
    assert parse_dask_address("tls://h:1") == ("remote", "tls://h:1")


def test_fill_cache_on_the_cluster_then_no_eigensolve(data, cluster, tmp_path):
    from torchheat.datasets import Preprocess, folder

    _, meshes, _ = data
    shapes = folder(meshes, preprocess=Preprocess(k=30), cache_dir=tmp_path / "cache")
    with deadline(120):
        done = shapes.fill_cache(cluster)
    assert [d["name"] for d in done] == shapes.names
    assert all(d["computed"] for d in done)
    hosts = {d["host"] for d in done}
    assert set(cluster.client.run(os.getpid).values()) >= {int(h.split(":")[1]) for h in hosts}
    assert not any(d["computed"] for d in shapes.fill_cache(cluster))


def test_missing_dask_gives_install_hint(monkeypatch):
    import builtins

    real = builtins.__import__

    def no_distributed(name, *a, **k):
        if name == "distributed" or name.startswith("distributed."):
            raise ImportError("No module named 'distributed'")
        return real(name, *a, **k)

    monkeypatch.setattr(builtins, "__import__", no_distributed)
    with pytest.raises(ImportError, match=r"pip install 'torchheat\[dask\]'"):
        DaskExecutor("local:1")


def test_scheduler_without_workers_fails_in_bounded_time():
    with deadline(60), distributed.LocalCluster(n_workers=0, processes=False,
                                                dashboard_address=":0") as empty:
        t0 = time.monotonic()
        with pytest.raises(ExecutorError, match="no Dask worker joined the scheduler at "
                                                f"{empty.scheduler_address} within 2 s"):
            DaskExecutor(empty.scheduler_address, workers_timeout=2)
        assert time.monotonic() - t0 < 20


def test_a_pair_that_kills_its_workers_becomes_an_error_record():
    from types import SimpleNamespace

    from distributed.scheduler import KilledWorker

    worker = SimpleNamespace(address="tcp://10.0.0.5:4711")
    task = SimpleNamespace(key="a-b#123", name="a-b")
    rec = batch._error_record(task, KilledWorker("pair-a-b-1234", worker, 3))
    assert rec["key"] == "a-b#123" and rec["name"] == "a-b"
    assert rec["error"].startswith("distributed.scheduler.KilledWorker: Attempted to run task")
    assert "tcp://10.0.0.5:4711" in rec["error"] and "\n" not in rec["error"]
    assert rec["error"].endswith("(killed, or out of memory: see the workers' logs)")
