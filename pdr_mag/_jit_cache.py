"""Keep numba's on-disk cache of a kernel fresh when any module it is built from changes.

numba (``cache=True``) checks a cached function against its own source file only: a kernel that calls
compiled functions of other modules keeps their old machine code after those modules change (numba's
documented limitation of caching).  :func:`refresh_if_changed` compares a digest of the sources of all
the modules a kernel is built from with the digest recorded beside the cache at the last check; when it
differs, it empties the cache of every compiled function of those modules (``Dispatcher.recompile``:
each is compiled afresh at its next call) and records the new digest.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

from numba.core.registry import CPUDispatcher


def refresh_if_changed(modules, name: str) -> bool:
    """Empty the numba caches of ``modules`` if their sources changed since the last call; True if so.

    The digest is kept in ``__pycache__/<name>.sources`` beside the first module (where numba keeps its
    cache); where that folder is not writable nothing is done (numba then caches elsewhere, per file).
    """
    h = hashlib.sha256()
    for mod in modules:
        h.update(Path(mod.__file__).read_bytes())
    digest = h.hexdigest()
    cache_dir = Path(modules[0].__file__).parent / "__pycache__"
    stamp = cache_dir / f"{name}.sources"
    try:
        if stamp.read_text() == digest:
            return False
    except OSError:
        pass
    try:
        cache_dir.mkdir(exist_ok=True)
    except OSError:
        return False
    if not os.access(cache_dir, os.W_OK):
        return False
    for mod in modules:
        for obj in vars(mod).values():
            if isinstance(obj, CPUDispatcher) and obj.py_func.__module__ == mod.__name__:
                obj.recompile()
    try:
        stamp.write_text(digest)
    except OSError:
        pass
    return True
