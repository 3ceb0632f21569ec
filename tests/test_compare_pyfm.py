"""scripts/compare_pyfm.py: its Princeton metric against a brute-force reference (great-circle
distances on a sphere) and its flip-aware choice (pyFM itself is not needed)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh
from conftest import load_script

from torchheat import Mesh

pytestmark = pytest.mark.filterwarnings("ignore:Sparse")


def _script():
    return load_script("compare_pyfm")


def test_princeton_errors_match_great_circle_distances():
    cp = _script()
    m = trimesh.creation.icosphere(4)
    V = np.asarray(m.vertices)
    V = V / np.linalg.norm(V, axis=1, keepdims=True)
    T = Mesh(V, np.asarray(m.faces))
    area = float(m.area)
    rng = np.random.default_rng(0)
    pred, gt = rng.integers(0, len(V), 60), rng.integers(0, len(V), 60)
    gt_sym = pred.copy()  # a "symmetric" ground truth the predictions follow exactly
    gt_sym[:3] = gt[:3]
    out = cp.princeton(T, pred, gt, gt_sym)
    ref = np.arccos(np.clip((V[pred] * V[gt]).sum(1), -1, 1)) / math.sqrt(area)
    assert np.abs(out["direct"] - ref).max() < 0.02  # heat-method geodesics, 2562 vertices
    assert np.corrcoef(out["direct"], ref)[0, 1] > 0.999
    # flip-aware: the whole map is judged against the ground truth it follows better
    assert (out["flip"][3:] < 1e-6).all()
    out2 = cp.princeton(T, pred, gt, None)
    assert out2["flip"] is None


def test_evenly_spaced_rows():
    cp = _script()
    r = cp.rows(5000, 300)
    assert r.size == 300 and r[0] == 0 and r[-1] == 4999
    assert cp.rows(100, 300).tolist() == list(range(100))
