"""cdqn: controlled deep Q-learning.

Deep Q-learning is modelled, through the neural tangent kernel (NTK) of a wide
two-layer ReLU network, as an uncertain linear system whose states are
``Q1 = Q(s, a)`` and ``Q2 = max_a' Q(s', a')`` (Varga, Kulcsár and Haghir Chehreghani,
"Deep Q-learning: a robust control approach", IJRNC 2022).  A feedback controller injects
a control reward ``u(t)`` into the temporal-difference loss so that learning converges
without a target network or random replay.
"""

import hashlib
import os
from pathlib import Path

__version__ = "0.1.0"


def _numba_cache_dir() -> str:
    """A numba cache folder per version of cdqn's sources.

    numba's on-disk cache (``@njit(cache=True)``) is invalidated by a change of the function's
    own source file only, not of the compiled functions it calls from other modules (a
    population kernel inlines the controller and network row functions): after such a change
    it would load stale machine code.  Keying the cache folder by a hash of every source file
    makes any change of cdqn start a fresh cache.  ``NUMBA_CACHE_DIR`` set by the user wins.
    """
    root = Path(__file__).resolve().parent
    digest = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        digest.update(path.relative_to(root).as_posix().encode())
        digest.update(path.read_bytes())
    return str(cache_dir() / "numba" / digest.hexdigest()[:16])


def cache_dir() -> Path:
    """cdqn's folder of derived files, safe to delete: ``$XDG_CACHE_HOME/cdqn``
    (``~/.cache/cdqn``)."""
    return Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "cdqn"


os.environ.setdefault("NUMBA_CACHE_DIR", _numba_cache_dir())
