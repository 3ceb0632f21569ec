#!/usr/bin/env python
"""Batch evaluation over a dataset: ``python scripts/evaluate.py configs/tosca5k.yaml``.

Thin wrapper of :func:`torchheat.batch.main` (also ``torchheat evaluate``); options:
``CONFIG [--workers N] [--limit N] [--output DIR] [--no-progress]``. Re-running resumes.
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from torchheat.batch import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())
