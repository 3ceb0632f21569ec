"""Batch evaluation (torchheat.batch): output files, resume after a kill, partial lines."""

from __future__ import annotations

import csv
import json
import os
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import deformed_spheres, kill_after_first_record

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
SMOKE = ROOT / "configs" / "smoke.yaml"
needs_data = pytest.mark.skipif(
    not (SHARED / "tosca_remeshed_5k").is_dir(), reason="shared/data not available"
)

batch = pytest.importorskip("torchheat.batch")


def _config(tmp: Path, out: Path, **over) -> Path:
    cfg = yaml.safe_load(SMOKE.read_text())
    cfg.update(output=str(out), pictures=0, **over)
    cfg.setdefault("dataset_args", {})["root"] = str(SHARED)
    path = tmp / f"{out.name}.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


def _lines(out: Path) -> list[dict]:
    return [json.loads(s) for s in (out / "results.jsonl").read_text().splitlines()]


def _numbers(recs: list[dict]) -> dict[str, tuple]:
    return {r["name"]: (r["direct"], r["flip"], r["flip_choice"], r["landmarks"], r["curve"])
            for r in recs}


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """An uninterrupted run over the 3 smoke pairs (shared by the tests below)."""
    tmp = tmp_path_factory.mktemp("batch")
    out = tmp / "ref"
    cfg = _config(tmp, out)
    results = batch.run(cfg, progress=False)
    return tmp, out, cfg, results


@needs_data
def test_run_writes_lines_and_summary_and_rerun_does_nothing(reference, monkeypatch):
    tmp, out, cfg, results = reference
    assert [r["name"] for r in results] == ["cat0-cat1", "cat0-cat10", "cat0-cat2"]
    lines = _lines(out)
    assert len(lines) == 3 and {r["name"] for r in lines} == {r["name"] for r in results}
    for f in ("summary.md", "summary.csv", "curves.png"):
        assert (out / f).stat().st_size > 0
    r = lines[0]
    assert set(r["direct"]) == {"mean", "under_0.25", "under_0.1", "under_0.05", "exact"}
    assert r["flip_choice"] in ("direct", "symmetric") and r["flip"] is not None
    assert r["flip"]["mean"] <= r["direct"]["mean"]
    assert len(r["curve"]) == len(r["curve_thresholds"]) == len(batch.CURVE_THRESHOLDS)
    assert np.all(np.diff(r["curve"]) >= 0) and r["curve"][-1] == r["direct"]["under_0.25"]
    assert r["time_match"] > 0 and r["time_eval"] > 0 and r["landmark"] is not None
    # TOSCA's .vts rows contradict their neighbours' on well under 1 % of a cat pair's rows
    for rec in lines:
        assert 0.0 <= rec["gt_contradicted"] < 0.01
        assert set(rec["consistent"]) == set(rec["direct"])
        if rec["gt_contradicted"] == 0.0:
            assert rec["consistent"] == rec["direct"]

    calls = []
    monkeypatch.setattr(batch.task, "evaluate_pair", lambda *a, **k: calls.append(a))
    before = (out / "results.jsonl").read_bytes()
    again = batch.run(cfg, progress=False)
    assert calls == [] and (out / "results.jsonl").read_bytes() == before
    assert _numbers(again) == _numbers(results)


@needs_data
def test_disk_cache_gives_the_same_results(reference, monkeypatch):
    # the eigenbasis comes from the per-shape disk cache: written on the first run, read (no
    # eigensolve) on the second, and the results equal those of the uncached run
    tmp, _, _, results = reference
    cache = tmp / "shape-cache"
    batch.clear_caches()
    first = batch.run(_config(tmp, tmp / "cached1", cache=str(cache), limit=2), progress=False)
    files = sorted(cache.rglob("*.npz"))
    assert len(files) == 3  # cat0, cat1, cat10
    from torchheat import heat

    calls = []
    orig = heat.HeatKernel._eigensolve
    monkeypatch.setattr(heat.HeatKernel, "_eigensolve",
                        lambda self, k, **kw: calls.append(k) or orig(self, k, **kw))
    batch.clear_caches()
    second = batch.run(_config(tmp, tmp / "cached2", cache=str(cache), limit=2), progress=False)
    assert calls == []
    ref = {k: v for k, v in _numbers(results).items() if k in _numbers(first)}
    assert _numbers(first) == _numbers(second) == ref


@needs_data
def test_errors_match_evaluate_module(reference):
    """The union-of-sources evaluation equals torchheat.evaluate.geodesic_errors (the batch
    keeps its distance fields in float32: equal to float32 rounding)."""
    from torchheat import datasets
    from torchheat.evaluate import geodesic_errors

    pair = datasets.tosca_remeshed_5k(root=SHARED, classes=["wolf"])[0]
    rng = np.random.default_rng(0)
    rows = np.arange(0, len(pair.gt_src), 50)
    pred = rng.integers(0, pair.target.mesh.n_vertices, len(rows))
    gt, gs = pair.gt_tgt.numpy()[rows], pair.gt_sym_tgt.numpy()[rows]
    mine = batch._TargetGeodesics(pair.target.mesh).errors(pred, [gt, gs])
    for got, g in zip(mine, (gt, gs), strict=True):
        want = geodesic_errors(pair.target.mesh, pred, g)
        np.testing.assert_allclose(got, want, rtol=1e-7, atol=0)
        assert np.count_nonzero(got) == np.count_nonzero(want) > 0


@needs_data
def test_resume_after_sigkill(reference):
    tmp, ref_out, _, ref_results = reference
    out = tmp / "killed"
    cfg = _config(tmp, out)
    env = dict(os.environ, PYTHONWARNINGS="ignore")
    n_before = kill_after_first_record(
        [sys.executable, str(ROOT / "scripts" / "evaluate.py"), str(cfg), "--no-progress"],
        out / "results.jsonl", env=env)
    assert 1 <= n_before < 3
    resumed = batch.run(cfg, progress=False)
    lines = _lines(out)
    names = [r["name"] for r in lines]
    assert len(names) == len(set(names)) == 3
    assert set(names) == {r["name"] for r in ref_results}
    assert _numbers(lines) == _numbers(_lines(ref_out)) == _numbers(resumed)


@needs_data
def test_trailing_partial_line_is_repaired(reference, tmp_path):
    _, ref_out, _, ref_results = reference
    out = tmp_path / "partial"
    out.mkdir()
    full = (ref_out / "results.jsonl").read_bytes().splitlines(keepends=True)
    # two complete records, then half of the third (a kill in the middle of a write)
    (out / "results.jsonl").write_bytes(full[0] + full[1] + full[2][: len(full[2]) // 2])
    cfg = _config(tmp_path, out)
    results = batch.run(cfg, progress=False)
    lines = _lines(out)
    assert [r["name"] for r in lines[:2]] == [json.loads(full[i])["name"] for i in (0, 1)]
    assert len(lines) == 3 and len({r["name"] for r in lines}) == 3
    assert _numbers(results) == _numbers(ref_results)


@needs_data
def test_any_object_with_map_is_an_executor(reference, tmp_path):
    _, _, _, ref_results = reference

    class Reversed:  # results arrive out of order, like dask's as_completed
        calls = 0

        def map(self, fn, iterable):
            Reversed.calls += 1
            return [fn(t) for t in reversed(list(iterable))]

    out = tmp_path / "custom"
    results = batch.run(_config(tmp_path, out, limit=2), executor=Reversed(), progress=False)
    assert Reversed.calls == 1
    assert [r["name"] for r in results] == [r["name"] for r in ref_results[:2]]
    assert _numbers(results) == _numbers(ref_results[:2])
    assert len(_lines(out)) == 2


@needs_data
def test_worker_processes_give_the_same_results(reference, tmp_path):
    _, _, _, ref_results = reference
    out = tmp_path / "workers"
    results = batch.run(_config(tmp_path, out), workers=2, progress=False)
    assert _numbers(results) == _numbers(ref_results)
    assert len(_lines(out)) == 3
    # the shapes were solved once each (cat0, cat1, cat10, cat2) before the pairs, not by
    # the pairs' workers; each pair's preparation time carries its share of them: cat0's
    # solve is split over its three pairs, a target's goes to its one pair
    assert all(r["eigensolves"] == 0 for r in results)
    shares = {r["name"]: r["time_shapes"] for r in results}
    assert all(0 < shares[n] <= r["time_prepare"] for n, r in zip(shares, results, strict=True))
    assert not (out / batch.runner.SCRATCH).exists()  # the run's scratch cache is gone


@needs_data
def test_interrupted_worker_run_keeps_its_scratch_cache_for_the_resume(reference, tmp_path,
                                                                       monkeypatch, capsys):
    _, _, _, ref_results = reference
    out = tmp_path / "interrupted"
    cfg = _config(tmp_path, out)

    def fail(*a, **k):
        raise KeyboardInterrupt

    with monkeypatch.context() as m:
        m.setattr(batch.runner, "_append_lines", fail)  # the first record's write
        with pytest.raises(KeyboardInterrupt):
            batch.run(cfg, workers=2, progress=False)
    kept = sorted(p.name for p in (out / batch.runner.SCRATCH).glob("*.npz"))
    assert len(kept) == 4  # every shape solved before the first pair ended
    capsys.readouterr()
    results = batch.run(cfg, workers=2, progress=True)
    assert _numbers(results) == _numbers(ref_results)
    # the resume read the kept entries: no eigensolve, in the shape phase or in the pairs
    assert "eigensolves this run: 0 (0 in 4 shape tasks, 0 in pair tasks)" in \
        capsys.readouterr().err
    assert not (out / batch.runner.SCRATCH).exists()


@needs_data
def test_worker_processes_fill_the_configured_cache_first(reference, tmp_path):
    _, _, _, ref_results = reference
    cache = tmp_path / "cache"
    out = tmp_path / "cached"
    results = batch.run(_config(tmp_path, out, cache=str(cache)), workers=2, progress=False)
    assert _numbers(results) == _numbers(ref_results)
    assert len(list(cache.rglob("*.npz"))) == 4  # the four shapes, kept for later runs
    again = batch.run(_config(tmp_path, tmp_path / "cached2", cache=str(cache)), workers=2,
                      progress=False)
    assert _numbers(again) == _numbers(ref_results)
    assert all(r["eigensolves"] == 0 for r in again)


def _ident(task):
    import threading
    import time

    time.sleep(0.02)
    return task, threading.get_ident()


def test_affinity_pool_runs_a_targets_pairs_on_one_worker():
    from concurrent.futures import ThreadPoolExecutor

    pool = batch._AffinityPool(0)
    pool.pools = [ThreadPoolExecutor(max_workers=1) for _ in range(2)]  # threads: quick
    tasks = [(g, i) for g in "abcdefg" for i in range(4)]
    try:
        out = list(pool.run(_ident, tasks, key=lambda t: t[0]))
    finally:
        pool.shutdown()
    assert sorted(t for t, _ in out) == sorted(tasks)  # every pair once
    workers = {g: {w for (h, _), w in out if h == g} for g in "abcdefg"}
    assert len({w for _, w in out}) == 2  # both workers used
    # a target is split only when a free worker has no untouched target left (at the end);
    # a shared queue (what a plain pool does) alternates the workers within most targets
    assert sum(len(w) > 1 for w in workers.values()) <= 1


def test_worker_run_with_an_unreadable_shape_reports_its_pairs(tmp_path, capsys):
    # the shape phase does not stop the run: the pairs of a shape it could not solve fail
    # one by one, naming the file, and the others are the in-process run's records
    meshes = tmp_path / "meshes"
    deformed_spheres(meshes, n=3, subdivisions=2)  # blob0..2, 162 vertices
    (meshes / "blob9.off").write_text("OFF\n3 1 0\n0 0 0\n1 0 0\n")  # truncated
    cfg = {"name": "bad", "dataset": "folder", "task": "match", "pictures": 0,
           "dataset_args": {"path": str(meshes), "classes": ["blob"] * 4, "gt": "identity",
                            "pairs": [["blob0", "blob1"], ["blob9", "blob1"],
                                      ["blob1", "blob2"]]},
           "match": {"method": "paper"}, "prepare": {"k": 30}}
    ref = batch.run({**cfg, "output": str(tmp_path / "ref")}, progress=False)
    capsys.readouterr()
    got = batch.run({**cfg, "output": str(tmp_path / "out")}, workers=2, progress=False)
    err = capsys.readouterr().err
    assert "blob9-blob1: failed:" in err and "blob9.off" in err
    assert "1 of 3 pairs failed (re-run to retry)" in err
    assert [r["name"] for r in got] == [r["name"] for r in ref] == ["blob0-blob1", "blob1-blob2"]
    assert _numbers(got) == _numbers(ref)
    assert all(r["eigensolves"] == 0 and r["time_shapes"] > 0 for r in got)


def test_affinity_pool_maps_every_task_to_free_workers():
    from concurrent.futures import ThreadPoolExecutor

    pool = batch._AffinityPool(0)
    pool.pools = [ThreadPoolExecutor(max_workers=1) for _ in range(2)]
    tasks = list(range(9))
    try:
        out = list(pool.map_unordered(_ident, tasks))
    finally:
        pool.shutdown()
    assert sorted(t for t, _ in out) == tasks and len({w for _, w in out}) == 2


def test_load_results_ignores_partial_line(tmp_path):
    p = tmp_path / "results.jsonl"
    p.write_text('{"key": "a#1", "name": "a"}\n{"key": "b#1", "na')
    assert [r["key"] for r in batch.load_results(p, repair=False)] == ["a#1"]
    assert p.read_text().endswith('"na')  # untouched without repair
    assert [r["key"] for r in batch.load_results(p)] == ["a#1"]
    assert p.read_text() == '{"key": "a#1", "name": "a"}\n'


def _rec(name: str, cls: str, mean: float, u25: float, flip25: float | None, t: float) -> dict:
    d = {"mean": mean, "under_0.25": u25, "under_0.1": u25 / 2, "under_0.05": u25 / 4,
         "exact": 0.0}
    flip = None if flip25 is None else {**d, "under_0.25": flip25}
    thr = list(batch.CURVE_THRESHOLDS)
    return {"key": f"{name}#x", "name": name, "cls": cls, "direct": d, "flip": flip,
            "flip_choice": None if flip is None else "direct", "time_prepare": 0.0,
            "time_match": t, "time_eval": 1.0, "curve_thresholds": thr,
            "curve": list(np.linspace(0, u25, len(thr))),
            "flip_curve": None if flip is None else list(np.linspace(0, flip25, len(thr))),
            "distortion": None}


def test_summarize_run_per_class(tmp_path):
    recs = [_rec("cat0-cat1", "cat", 0.1, 0.8, 0.9, 2.0),
            _rec("cat0-cat2", "cat", 0.3, 0.4, 0.5, 4.0),
            _rec("dog0-dog1", "dog", 0.2, 0.6, None, 6.0)]
    overall = batch.summarize_run(recs, tmp_path)
    rows = {(r["level"], r["name"]): r for r in csv.DictReader(open(tmp_path / "summary.csv"))}
    cat, dog = rows[("class", "cat")], rows[("class", "dog")]
    assert int(cat["pairs"]) == 2 and float(cat["mean_error"]) == pytest.approx(0.2)
    assert float(cat["pct_under_0.25"]) == pytest.approx(60.0)
    assert float(cat["pct_under_0.1"]) == pytest.approx(30.0)
    assert float(cat["flip_pct_under_0.25"]) == pytest.approx(70.0)
    assert float(cat["time_per_pair_s"]) == pytest.approx(4.0)
    assert dog["flip_pct_under_0.25"] == "" and float(dog["pct_under_0.25"]) == pytest.approx(60)
    assert overall["pairs"] == 3 and overall["mean_error"] == pytest.approx(0.2)
    assert overall["flip_pct_under_0.25"] == pytest.approx(70.0)  # pairs with symmetric gt
    assert float(rows[("pair", "dog0-dog1")]["time_match_s"]) == pytest.approx(6.0)
    md = (tmp_path / "summary.md").read_text()
    assert "## Per class" in md and "| cat | 2 |" in md
    # where it was written: the BLAS build changes maps in their last bits (23rd session)
    import numpy
    import scipy

    import torchheat

    last = md.strip().splitlines()[-1]
    assert last.startswith(f"Written by torchheat {torchheat.__version__}")
    assert f"numpy {numpy.__version__}, scipy {scipy.__version__}" in last and "UTC" in last
    assert (tmp_path / "curves.png").stat().st_size > 0
    assert not list(tmp_path.glob(".*"))  # no temporary files left
    # records without contradicted ground truth (or written before the check): no such columns
    assert "GT contradicted %" not in md and rows[("class", "cat")]["gt_contradicted_pct"] == ""


def test_summary_counts_contradicted_ground_truth(tmp_path):
    recs = [_rec("vic0-vic1", "victoria", 0.05, 0.90, None, 2.0),
            _rec("vic0-vic2", "victoria", 0.02, 1.00, None, 2.0)]
    recs[0]["gt_contradicted"], recs[0]["consistent"] = 0.04, {
        **recs[0]["direct"], "mean": 0.03, "under_0.25": 0.98}
    recs[1]["gt_contradicted"], recs[1]["consistent"] = 0.0, recs[1]["direct"]
    overall = batch.summarize_run(recs, tmp_path)
    assert overall["gt_contradicted_pct"] == pytest.approx(2.0)
    assert overall["consistent_pct_under_0.25"] == pytest.approx(99.0)
    assert overall["consistent_mean_error"] == pytest.approx(0.025)
    assert overall["pct_under_0.25"] == pytest.approx(95.0)  # every row still counts there
    md = (tmp_path / "summary.md").read_text()
    assert "GT contradicted %" in md and "| all | 2 | 0.0350 | 95.0 |" in md
    assert md.count("| 2.00 | 99.0 | 0.0250 |") == 2  # overall and the class


@needs_data
def test_evaluate_line_names_contradicted_ground_truth(tmp_path, capsys, monkeypatch):
    cfg = _config(tmp_path, tmp_path / "line")
    recs = [_rec("cat0-cat1", "cat", 0.05, 0.90, None, 2.0),
            _rec("cat0-cat10", "cat", 0.02, 1.00, None, 2.0)]
    recs[0]["gt_contradicted"], recs[0]["consistent"] = 0.04, {
        **recs[0]["direct"], "under_0.25": 0.98}
    recs[1]["gt_contradicted"], recs[1]["consistent"] = 0.0, recs[1]["direct"]
    monkeypatch.setattr(batch.commands, "run", lambda *a, **k: recs)
    assert batch.main([str(cfg)]) == 1  # 2 of the config's 3 pairs
    out = capsys.readouterr().out
    assert "95.0% < 0.25" in out
    assert "99.0% on the rows whose ground truth agrees with its neighbours' (2.00% do not)" in out
    for r in recs:
        r["gt_contradicted"], r["consistent"] = 0.0, r["direct"]
    batch.main([str(cfg)])
    assert "neighbours" not in capsys.readouterr().out


def test_bad_config_gives_one_line_error(tmp_path, capsys):
    assert batch.main([str(tmp_path / "missing.yaml")]) == 2
    assert "not found" in capsys.readouterr().err
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: x\ndataset: nope\n")
    assert batch.main([str(bad)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error:") and "dataset" in err and "\n" not in err
    bad.write_text("name: x\ndataset: scape\nlimt: 3\n")
    assert batch.main([str(bad)]) == 2
    assert "unknown keys" in capsys.readouterr().err
    # a folder of meshes has no ground truth but the vertex order: it must be said
    bad.write_text(f"name: x\ndataset: folder\ndataset_args: {{path: {tmp_path}, "
                   "pairs: [[a, b]]}\n")
    assert batch.main([str(bad)]) == 2
    err = capsys.readouterr().err
    assert "needs dataset_args.gt: identity" in err and "torchheat match" in err
    bad.write_text(f"name: x\ndataset: folder\ndataset_args: {{path: {tmp_path}, "
                   "pairs: [[a, b]], gt: identiy}\n")  # a typo is refused the same way
    assert batch.main([str(bad)]) == 2
    assert "got 'identiy'" in capsys.readouterr().err
    # match options are checked before any pair runs (a typo failed every pair, each after
    # its eigensolves)
    for opts, text in (("{zoomot: false}", "unknown match option 'zoomot' (did you mean "
                                           "'zoomout'?)"),
                       ("{refine_samples: 0}", "refine_samples=0: must be at least 1")):
        bad.write_text(f"name: x\ndataset: scape\nmatch: {opts}\n")
        assert batch.main([str(bad)]) == 2
        err = capsys.readouterr().err
        assert f"bad.yaml: match: {text}" in err and "\n" not in err.strip()
    for opts, text in (("{k: 5.5}", "k must be an integer, not 5.5"),
                       ("{feature_time: -3}", "feature_time=-3: must be positive"),
                       ("{kind: cot}", "unknown Laplacian kind 'cot'")):
        bad.write_text(f"name: x\ndataset: scape\nprepare: {opts}\n")
        assert batch.main([str(bad)]) == 2
        err = capsys.readouterr().err
        assert f"bad.yaml: prepare: {text}" in err and "\n" not in err.strip()


def test_roles_share_one_eigensolve_but_not_their_times():
    import torch
    import trimesh

    from torchheat import Mesh

    class _Shape:  # the attributes _prepared reads from a datasets.Shape
        name, path, data = "ico", "", None

        def __init__(self):
            m = trimesh.creation.icosphere(3)
            self.mesh = Mesh(m.vertices * [1.0, 0.8, 0.6], m.faces)

    batch.clear_caches()
    shape = _Shape()
    src = batch._prepared(shape, "source", {}, {"k": 30})
    tgt = batch._prepared(shape, "target", {}, {"k": 30})
    assert src is not tgt and src.hk is not tgt.hk
    assert np.shares_memory(src.hk._phi_red, tgt.hk._phi_red)  # one eigensolve
    t_src = src.hk.times.clone()
    with pytest.warns(DeprecationWarning, match="with_times"):
        tgt.hk.set_times(t_src * 2)  # the deprecated in-place re-plan
    assert torch.equal(src.hk.times, t_src)
    assert batch._prepared(shape, "source", {}, {"k": 30}) is src  # memoised per role
    batch.clear_caches()


def test_preprocess_command_fills_the_cache_once(tmp_path, capsys):
    from conftest import deformed_spheres

    deformed_spheres(tmp_path / "m", n=3, subdivisions=2)
    argv = [str(tmp_path / "m"), "--cache", str(tmp_path / "c"), "--k", "8", "--no-progress"]
    assert batch.preprocess_main(argv) == 0
    assert "3 shapes: 3 computed, 0 already cached" in capsys.readouterr().out
    assert len(list((tmp_path / "c").glob("*.npz"))) == 3
    assert batch.preprocess_main(argv) == 0
    assert "3 shapes: 0 computed, 3 already cached" in capsys.readouterr().out
    assert batch.preprocess_main([str(tmp_path / "nothere")]) == 2
    assert "no such config file or folder of meshes" in capsys.readouterr().err


@needs_data
def test_an_ambiguous_choice_records_its_rival_map(monkeypatch):
    # every choice read as ambiguous: the record scores the rival map like the direct map
    from torchheat import datasets
    from torchheat.matching import match, quality

    monkeypatch.setattr(quality, "AMBIGUOUS_BELOW", float("inf"))
    pair = datasets.tosca_remeshed_5k(root=SHARED, classes=["wolf"])[0]
    rec = batch.evaluate_pair(pair, {}, eval_points=100)
    assert rec["ambiguous"] is True and rec["margin"] is not None
    corr = match(pair.source.mesh, pair.target.mesh)
    rows = np.unique(np.linspace(0, len(pair.gt_src) - 1, 100).round().astype(np.int64))
    gs, gt = pair.gt_src.numpy()[rows], pair.gt_tgt.numpy()[rows]
    err = batch._TargetGeodesics(pair.target.mesh).errors(corr.rival_map.numpy()[gs], [gt])[0]
    assert rec["rival"]["mean"] == pytest.approx(float(err.mean()), rel=1e-6)
    assert rec["direct"]["under_0.25"] > 0.9 > rec["rival"]["under_0.25"]  # a different map
    row = batch._row("overall", "all", [rec, {**rec, "rival": {"under_0.25": 1.0}}])
    assert row["ambiguous"] == 2 and row["rival_right"] == 1
    # which search gave the map is recorded and counted (match(staged=True))
    assert rec["search"] in ("first stage", "full (first stage not clear)")
    gap = corr.info["near_gap"]  # same pair, same choice: the same gap, in the report too
    assert (rec["near_gap"] is None) == (gap is None) == ("near_gap" not in corr.report())
    if gap is not None:
        assert rec["near_gap"] == pytest.approx(gap) == corr.report()["near_gap"]
    two = [{**rec, "search": "first stage"}, {**rec, "search": "full (first stage not clear)"}]
    assert batch._row("overall", "all", two)["first_stage"] == 1
    assert batch._row("overall", "all", [{**rec, "search": None}])["first_stage"] is None


@pytest.mark.parametrize("path", sorted((ROOT / "configs").glob("*.yaml")), ids=lambda p: p.name)
def test_every_shipped_config_loads(path):
    # each config names a loader of torchheat.datasets and passes load_config's checks; a
    # dataset of high-resolution shapes evaluates a subset of points (every vertex of TOSCA
    # high-res or KIDS would take minutes per pair)
    from torchheat import datasets
    from torchheat.batch.config import load_config

    cfg = load_config(path)
    assert callable(getattr(datasets, cfg["dataset"]))
    if cfg["dataset"] in ("tosca_hires", "kids"):
        assert cfg["eval_points"] is not None and cfg["eval_points"] <= 5000


def test_load_pairs_gives_the_pairs_a_run_records(tmp_path):
    # the pairs of a config, in the run's order and with its limit, and each pair's ground
    # truth as the run reads it (here: identity maps of deformed spheres)
    meshes = tmp_path / "meshes"
    deformed_spheres(meshes, n=3, subdivisions=2)
    cfg = {"name": "lp", "dataset": "folder", "task": "match", "pictures": 0,
           "dataset_args": {"path": str(meshes), "classes": ["blob"] * 3, "gt": "identity",
                            "pairs": [["blob0", "blob1"], ["blob2", "blob0"],
                                      ["blob1", "blob2"]]},
           "match": {"method": "paper"}, "prepare": {"k": 30}}
    pairs = batch.load_pairs(cfg)
    assert pairs.names == ["blob0-blob1", "blob2-blob0", "blob1-blob2"]
    p = pairs[1]
    assert p.source.name == "blob2" and p.target.name == "blob0"
    assert np.array_equal(np.asarray(p.gt_src), np.asarray(p.gt_tgt))
    first = batch.load_pairs({**cfg, "limit": 2})
    assert first.names == ["blob0-blob1", "blob2-blob0"] and len(first) == 2
    assert len(batch.load_pairs(cfg)) == 3  # the run's cached collection keeps every pair
    path = tmp_path / "lp.yaml"
    path.write_text(yaml.safe_dump({**cfg, "limit": 1, "output": str(tmp_path / "out")}))
    recs = batch.run(path, progress=False)
    assert [r["name"] for r in recs] == batch.load_pairs(path).names == ["blob0-blob1"]
