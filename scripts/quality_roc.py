"""How well a map's quality (no ground truth) separates wrong maps from right ones.

Reads the ``results.jsonl`` of batch evaluation runs (``torchheat evaluate``), splits the maps
into wrong (< 50 % of the evaluated points under 0.25, direct ground truth) and right
(> 90 %), and prints the ROC curve's area, the suspect flag's recall on wrong maps and its
false-alarm rate on right ones; the same for the choice's margin (the best rival's score gap,
``MapQuality.margin``: a missing margin, no rival, counts as large) and the ambiguous flag,
where the runs recorded them; writes the ROC curves as a PNG.

    python scripts/quality_roc.py out/tosca5k/results.jsonl out/scape/results.jsonl \\
        --png docs/quality_roc.png
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def load(paths: list[str]) -> list[dict]:
    recs = []
    for p in paths:
        for line in Path(p).read_text().splitlines():
            if line.strip():
                r = json.loads(line)
                if r.get("quality") is not None and r.get("direct"):
                    r["_run"] = Path(p).parent.name
                    recs.append(r)
    return recs


def roc(q_wrong: np.ndarray, q_right: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """ROC of flagging a map when its quality is below a threshold: (false-alarm rate on
    right maps, detection rate on wrong maps) over all thresholds, and the AUC (the
    probability that a wrong map scores below a right one, ties counted half)."""
    thr = np.unique(np.concatenate([q_wrong, q_right, [-np.inf, np.inf]]))
    hit = np.array([(q_wrong < t).mean() for t in thr] + [1.0])
    fa = np.array([(q_right < t).mean() for t in thr] + [1.0])
    auc = (q_wrong[:, None] < q_right[None, :]).mean() \
        + 0.5 * (q_wrong[:, None] == q_right[None, :]).mean()
    return fa, hit, float(auc)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("results", nargs="+")
    ap.add_argument("--png", default=None)
    args = ap.parse_args()
    recs = load(args.results)
    acc = np.array([r["direct"]["under_0.25"] for r in recs])
    q = np.array([r["quality"] for r in recs])
    sus = np.array([bool(r["suspect"]) for r in recs])
    wrong, right = acc < 0.5, acc > 0.9
    print(f"{len(recs)} maps: {right.sum()} right (> 90 % under 0.25), {wrong.sum()} wrong "
          f"(< 50 %), {len(recs) - right.sum() - wrong.sum()} in between")
    for run in sorted({r["_run"] for r in recs}):
        sel = np.array([r["_run"] == run for r in recs])
        print(f"  {run}: {sel.sum()} maps, {(right & sel).sum()} right, {(wrong & sel).sum()} "
              f"wrong, suspect {(sus & sel).sum()}")
    if wrong.any() and right.any():
        fpr, tpr, auc = roc(q[wrong], q[right])
        print(f"ROC AUC (right vs wrong by quality): {auc:.3f}")
        print(f"suspect flag: {sus[wrong].mean() * 100:.1f} % of wrong maps flagged, "
              f"{sus[right].mean() * 100:.1f} % of right maps flagged (false alarms)")
        mg = np.array([np.inf if r.get("margin") is None else r["margin"] for r in recs])
        has_margin = any(r.get("ambiguous") is not None for r in recs)
        if has_margin:
            amb = np.array([bool(r.get("ambiguous")) for r in recs])
            fpr_m, tpr_m, auc_m = roc(mg[wrong], mg[right])
            print(f"ROC AUC (right vs wrong by the choice's margin): {auc_m:.3f}")
            print(f"ambiguous flag: {amb[wrong].mean() * 100:.1f} % of wrong maps flagged, "
                  f"{amb[right].mean() * 100:.1f} % of right maps flagged")
            either = amb | sus
            print(f"suspect or ambiguous: {either[wrong].mean() * 100:.1f} % of wrong maps, "
                  f"{either[right].mean() * 100:.1f} % of right maps")
        if args.png:
            import matplotlib

            matplotlib.use("Agg")
            import matplotlib.pyplot as plt

            fig, ax = plt.subplots(figsize=(4.5, 4.5))
            ax.plot(fpr, tpr, lw=2, label=f"quality (AUC {auc:.3f})")
            ax.plot([0, 1], [0, 1], ":", color="grey")
            ax.scatter([sus[right].mean()], [sus[wrong].mean()], color="red", zorder=3,
                       label="suspect flag (quality < 0.25)")
            if has_margin:
                ax.plot(fpr_m, tpr_m, lw=2, label=f"choice margin (AUC {auc_m:.3f})")
                ax.scatter([amb[right].mean()], [amb[wrong].mean()], color="black",
                           marker="s", zorder=3, label="ambiguous flag (margin < 0.15)")
            ax.set_xlabel("right maps called wrong (false alarms)")
            ax.set_ylabel("wrong maps detected")
            ax.set_title(f"{right.sum()} right vs {wrong.sum()} wrong maps")
            ax.legend(loc="lower right", fontsize=8)
            fig.tight_layout()
            fig.savefig(args.png, dpi=110)
            print(f"ROC curve written to {args.png}")
    else:
        print("no wrong maps (or no right ones): no ROC; suspect on "
              f"{sus.sum()} of {len(recs)} maps")


if __name__ == "__main__":
    main()
