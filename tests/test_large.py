"""Real meshes at full size through the command line (the 60k regression) and the eigenpair
check on real poses. Skipped where ../shared/data is absent."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import SHARED

from torchheat import Mesh, laplacian
from torchheat.eigen import cotan_eigenpairs, face_areas
from torchheat.heat import _check_eigenpairs
from torchheat.meshio import read_arrays

KIDS = SHARED / "kids"
SCAPE = SHARED / "scape"


@pytest.mark.slow
@pytest.mark.skipif(not (KIDS / "0001.null.0.off").exists(), reason="shared KIDS data absent")
def test_cli_default_options_on_a_60k_pair(tmp_path):
    # default options, forked eigensolves, eigenpair check: a late 'safety' check once made
    # this exit 1 on every ~60k mesh. Same vertex order on both poses: ground truth = identity.
    src, tgt = KIDS / "0001.null.0.off", KIDS / "0001.isometry.1.off"
    out = tmp_path / "m.txt"
    exe = Path(sys.executable).parent / "torchheat"
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "torchheat.cli"]
    res = subprocess.run([*cmd, "match", str(src), str(tgt), "-o", str(out)],
                         capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr
    assert "Traceback" not in res.stderr and "arning" not in res.stderr
    V, F = read_arrays(tgt)
    m = np.loadtxt(out, dtype=np.int64)
    assert m.shape == (V.shape[0],) and V.shape[0] >= 50_000
    # Euclidean distance bounds the geodesic one from below; measured: mean 0.025, 100 %
    err = np.linalg.norm(V[m] - V, axis=1) / np.sqrt(face_areas(V, F).sum())
    assert (err < 0.25).mean() >= 0.97 and err.mean() <= 0.06


@pytest.mark.skipif(not (SCAPE / "mesh001.off").exists(), reason="shared SCAPE data absent")
def test_eigenpair_check_on_real_poses():
    # 12.5k vertices, two poses with the same connectivity: each pose's own ARPACK pairs pass,
    # the other pose's are refused (they are nearly eigenpairs: a hard case for the check)
    V0, F0 = read_arrays(SCAPE / "mesh000.off")
    V1, F1 = read_arrays(SCAPE / "mesh001.off")
    lam, phi = cotan_eigenpairs(V0, F0, k=100)
    own = Mesh(V0, F0, name="mesh000.off")
    _check_eigenpairs(*laplacian(own).reduced(), lam, phi, own)
    other = Mesh(V1, F1, name="mesh001.off")
    with pytest.raises(ValueError, match="mesh001.off: the given eigenpairs are not those"):
        _check_eigenpairs(*laplacian(other).reduced(), lam, phi, other)
