"""Summaries of a run's records: ``summary.md`` / ``summary.csv`` (overall, per class, per
pair), the mean cumulative curves PNG and colour-transfer pictures.
"""

from __future__ import annotations

import csv
import functools
import io
import math
import os
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .._files import atomic_write
from .caches import _load_dataset
from .results import _write_text

# --------------------------------------------------------------------------------------------
# summary
# --------------------------------------------------------------------------------------------
_COLUMNS = ("level", "name", "pairs", "mean_error", "pct_under_0.25", "pct_under_0.1",
            "pct_under_0.05", "flip_pct_under_0.25", "flip_mean_error", "symmetric_choices",
            "time_match_s", "time_eval_s", "time_per_pair_s", "distortion",
            "gt_contradicted_pct", "consistent_pct_under_0.25", "consistent_mean_error")


def _nanmean(vals: Sequence[float | None]) -> float | None:
    v = [float(x) for x in vals if x is not None and not math.isnan(float(x))]
    return float(np.mean(v)) if v else None


def _row(level: str, name: str, recs: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    def d(key: str, scale: float = 1.0, sub: str = "direct") -> float | None:
        m = _nanmean([None if r.get(sub) is None else r[sub][key] for r in recs])
        return None if m is None else m * scale

    flips = [r for r in recs if r.get("flip") is not None]
    return {
        "level": level,
        "name": name,
        "pairs": len(recs),
        "mean_error": d("mean"),
        "pct_under_0.25": d("under_0.25", 100),
        "pct_under_0.1": d("under_0.1", 100),
        "pct_under_0.05": d("under_0.05", 100),
        "flip_pct_under_0.25": d("under_0.25", 100, "flip"),
        "flip_mean_error": d("mean", 1.0, "flip"),
        "symmetric_choices": sum(r.get("flip_choice") == "symmetric" for r in flips)
        if flips else None,
        "time_match_s": _nanmean([r.get("time_prepare", 0.0) + r["time_match"] for r in recs]),
        "time_eval_s": _nanmean([r["time_eval"] for r in recs]),
        "time_per_pair_s": _nanmean([r.get("time_prepare", 0.0) + r["time_match"]
                                     + r["time_eval"] for r in recs]),
        "distortion": _nanmean([r.get("distortion") for r in recs]),
        # rows whose ground truth contradicts its neighbours' (evaluate.gt_disagreement), and
        # the direct figures on the others (records written before it have neither)
        "gt_contradicted_pct": _nanmean([None if r.get("gt_contradicted") is None
                                         else 100 * r["gt_contradicted"] for r in recs]),
        "consistent_pct_under_0.25": d("under_0.25", 100, "consistent"),
        "consistent_mean_error": d("mean", 1.0, "consistent"),
        "quality": _nanmean([r.get("quality") for r in recs]),
        "suspect": sum(bool(r.get("suspect")) for r in recs)
        if any(r.get("suspect") is not None for r in recs) else None,
        "ambiguous": sum(bool(r.get("ambiguous")) for r in recs)
        if any(r.get("ambiguous") is not None for r in recs) else None,
        # ambiguous pairs whose rival map (Correspondence.rival_map) is right (>= 90 % < 0.25)
        "rival_right": sum((r.get("rival") or {}).get("under_0.25", 0.0) >= 0.9 for r in recs)
        if any(r.get("ambiguous") is not None for r in recs) else None,
        # maps of a staged search kept from its first stage (match(staged=True))
        "first_stage": sum(r.get("search") == "first stage" for r in recs)
        if any(r.get("search") for r in recs) else None,
    }


def _table_rows(results: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    rows = [_row("overall", "all", results)]
    classes: dict[str, list] = {}
    for r in results:
        classes.setdefault(r["cls"], []).append(r)
    rows += [_row("class", c, rs) for c, rs in classes.items()]
    rows += [_row("pair", r["name"], [r]) for r in results]
    return rows


def _fmt(v: Any, digits: int = 3) -> str:
    if v is None:
        return "—"
    if isinstance(v, float):
        return f"{v:.{digits}f}"
    return str(v)


def _markdown(rows: list[dict[str, Any]], title: str) -> str:
    head = ["name", "pairs", "mean err", "% <0.25", "% <0.1", "% <0.05", "flip % <0.25",
            "sym. chosen", "match s", "eval s", "s / pair"]
    keys = ["name", "pairs", "mean_error", "pct_under_0.25", "pct_under_0.1", "pct_under_0.05",
            "flip_pct_under_0.25", "symmetric_choices", "time_match_s", "time_eval_s",
            "time_per_pair_s"]
    digits = {"mean_error": 4, "pct_under_0.25": 1, "pct_under_0.1": 1, "pct_under_0.05": 1,
              "flip_pct_under_0.25": 1, "time_match_s": 2, "time_eval_s": 2,
              "time_per_pair_s": 2}
    if any(r.get("quality") is not None for r in rows):
        head += ["quality", "suspect", "ambiguous", "rival right"]
        keys += ["quality", "suspect", "ambiguous", "rival_right"]
        digits["quality"] = 2
    if any(r.get("first_stage") is not None for r in rows):
        head.append("1st stage")
        keys.append("first_stage")
    if any(r["gt_contradicted_pct"] for r in rows):  # only where the ground truth has such rows
        head += ["GT contradicted %", "consistent % <0.25", "consistent mean err"]
        keys += ["gt_contradicted_pct", "consistent_pct_under_0.25", "consistent_mean_error"]
        digits.update({"gt_contradicted_pct": 2, "consistent_pct_under_0.25": 1,
                       "consistent_mean_error": 4})
    if any(r["distortion"] is not None for r in rows):
        head.append("distortion")
        keys.append("distortion")
        digits["distortion"] = 4
    lines = [f"# {title}", "",
             "Errors: geodesic distance to the ground truth / sqrt(target area) (Kim et al. "
             "2011), averaged per pair, then over pairs (every pair weighs the same). "
             "Flip-aware: the direct or the symmetric ground truth, whichever fits the whole "
             "map better. Times: prepare + match (prepare includes the pair's share of the "
             "eigensolves run once per shape before the pairs, where they were), evaluation. "
             "Quality: the map's own evidence "
             "(0..1, no ground truth; torchheat.matching.quality), suspect: maps below 0.25, "
             "ambiguous: maps whose best rival (a different whole map) scored within 0.15, "
             "rival right: ambiguous maps whose rival map is right (>= 90 % under 0.25); "
             "1st stage: maps kept from the first stage of the staged search. GT "
             "contradicted (where shown): evaluated rows whose ground-truth image lies over "
             "0.1 sqrt(area) from its neighbours' images (torchheat.evaluate.gt_disagreement; "
             "no continuous map is right on both), and the direct figures on the other rows; "
             "the columns before them count every row.",
             ""]
    for level, label in (("overall", "Overall"), ("class", "Per class"), ("pair", "Per pair")):
        sel = [r for r in rows if r["level"] == level]
        if not sel:
            continue
        lines += [f"## {label}", "", "| " + " | ".join(head) + " |",
                  "|" + "---|" * len(head)]
        for r in sel:
            lines.append("| " + " | ".join(_fmt(r[k], digits.get(k, 3)) for k in keys) + " |")
        lines.append("")
    return "\n".join(lines)


def _mean_curves(results: Sequence[Mapping[str, Any]]) -> dict[str, tuple]:
    curves: dict[str, tuple] = {}
    for key, label in (("curve", "direct"), ("flip_curve", "flip-aware")):
        cs = [(r["curve_thresholds"], r[key]) for r in results if r.get(key) is not None]
        cs = [c for c in cs if list(c[0]) == list(cs[0][0])] if cs else []
        if cs:
            curves[f"{label} ({len(cs)} pairs)"] = (
                np.asarray(cs[0][0]), np.mean([np.asarray(c[1]) for c in cs], axis=0))
    return curves


def summarize_run(
    results: Sequence[Mapping[str, Any]],
    output: str | os.PathLike,
    config: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """Write ``summary.md``, ``summary.csv``, ``curves.png`` (and pictures) for a run.

    Parameters
    ----------
    results : sequence of dict
        Records of :func:`evaluate_pair` / ``results.jsonl``.
    output : path-like
        Folder to write into (created).
    config : mapping, optional
        The run config; with ``pictures > 0`` and :mod:`torchheat.viz` available, colour
        transfer PNGs of the first pairs whose maps were saved (``maps/<name>.npz``) are written
        to ``pictures/``.

    Returns
    -------
    dict
        The overall row (``mean_error``, ``pct_under_0.25``, ..., ``time_per_pair_s``).

    Notes
    -----
    Per-class and overall figures are means over pairs of the per-pair figures. Percentages
    are 0-100. ``summary.md`` ends with where it was written (versions, git commit, BLAS, CPU:
    :func:`torchheat._provenance.provenance`; maps depend on the BLAS build in their last
    bits). The CSV holds one row per level (``overall``, ``class``, ``pair``). All files
    are written atomically (temporary file + :func:`os.replace`).

    Examples
    --------
    >>> from torchheat.batch import load_results
    >>> summarize_run(load_results("out/smoke/results.jsonl"), "out/smoke")  # doctest: +SKIP
    """
    from ..evaluate import plot_cumulative

    out = Path(output)
    out.mkdir(parents=True, exist_ok=True)
    if not results:
        raise ValueError("no results to summarize")
    rows = _table_rows(results)
    title = (config or {}).get("name") or out.name
    from .._provenance import provenance_line

    _write_text(out / "summary.md", _markdown(rows, f"{title}: {len(results)} pairs") + "\n"
                + provenance_line() + " (A resumed run keeps the records of the runs before "
                "it.)\n")
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(_COLUMNS), lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: "" if r[k] is None else r[k] for k in _COLUMNS})
    _write_text(out / "summary.csv", buf.getvalue())
    curves = _mean_curves(results)
    if curves:
        atomic_write(out / "curves.png",
                     lambda t: plot_cumulative(curves, t, title=f"{title}: mean cumulative "
                                               f"error ({len(results)} pairs)"))
    if config is not None and int(config.get("pictures", 0)) > 0:
        _pictures(results, out, config)
    return rows[0]


def _pictures(results: Sequence[Mapping[str, Any]], out: Path, cfg: Mapping[str, Any]) -> None:
    try:
        from .. import viz
    except ImportError:
        return
    color_transfer = getattr(viz, "color_transfer", None)
    if color_transfer is None:
        return
    pc = _load_dataset(cfg["dataset"], cfg["dataset_args"])  # meshes only: no eigensolve here
    index = {n: i for i, n in enumerate(pc.names)}
    for rec in results[: int(cfg["pictures"])]:
        png = out / "pictures" / f"{rec['name']}.png"
        maps = out / "maps" / f"{rec['name']}.npz"
        if png.exists() or not maps.is_file() or rec["name"] not in index:
            continue
        try:
            with np.load(maps) as z:
                fmap = z["map"]
            pair = pc[index[rec["name"]]]
            d = rec["direct"] if rec.get("flip") is None else rec["flip"]
            title = f"{rec['name']}: {100 * d['under_0.25']:.0f}% < 0.25"
            atomic_write(png, functools.partial(color_transfer, pair.source.mesh,
                                                pair.target.mesh, fmap, title=title))
        except Exception as exc:  # noqa: BLE001 - pictures are optional
            warnings.warn(f"picture for {rec['name']} failed: {exc}", stacklevel=2)
