"""damcap's studies (slow; never in CI): each module runs one, from the repository root, as
``.venv/bin/python -m bench.<study>`` (``make bench`` runs several), and writes
``bench/results/<study>.json`` and ``bench/<study>.md``. :mod:`bench.common` holds what they share;
``tests/bench/`` runs each at tiny sizes."""

import damcap  # noqa: E402,F401  (first: damcap sets OpenMP's wait policy before any study imports torch)
