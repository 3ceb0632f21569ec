"""``python -m torchheat``: the ``torchheat`` command (:func:`torchheat.cli.run`), for an
environment whose scripts folder is not on ``PATH``."""

from .cli import run

if __name__ == "__main__":
    run()
