"""numba's decorators of the fused kernel, and its disk cache, kept fresh across the files.

Every function of the kernel is compiled with :data:`scalar_jit` or :data:`loop_jit`
(``cache=True``). numba keys a cached kernel on the source of the file that defines it
and not on the files of the functions it calls (numba's documentation says so): with the
kernel split across the files of this package, a change to ``network.py`` would leave
``fused_step``'s cached code in use. So the functions of this package are cached with
locators whose source stamp is :func:`kernels_source_stamp`, a hash of every file here:
any change to any of them recompiles every kernel. The cache lies where numba would put
it otherwise (``NUMBA_CACHE_DIR``, else the package's ``__pycache__``, else the user's
cache folder); functions outside this package keep numba's own locators. (Where
``NUMBA_CACHE_LOCATOR_CLASSES`` is set, numba uses those locators instead.)
"""

from __future__ import annotations

import functools
import hashlib
from pathlib import Path
from typing import Any

from numba import njit
from numba.core.caching import (
    CacheImpl,
    InTreeCacheLocator,
    UserProvidedCacheLocator,
    UserWideCacheLocator,
)

__all__ = ["FM", "KERNELS_DIR", "kernels_source_stamp", "loop_jit", "scalar_jit"]

KERNELS_DIR = Path(__file__).resolve().parent
"""The folder of the kernel's files."""

FM = {"nsz", "reassoc", "contract"}
"""fastmath flags of the loops: reassociation (vectorised sums), FMA, signed zeros. Not
``nnan``/``ninf``: a non-finite member must stay non-finite."""


def kernels_source_stamp(folder: Path = KERNELS_DIR) -> str:
    """sha256 over the names and contents of every ``*.py`` file of ``folder``."""
    stats = [(p.name, p.stat()) for p in sorted(folder.glob("*.py"))]
    return _stamp(folder, tuple((name, st.st_mtime_ns, st.st_size) for name, st in stats))


@functools.lru_cache(maxsize=8)
def _stamp(folder: Path, files: tuple[tuple[str, int, int], ...]) -> str:
    """The hash of :func:`kernels_source_stamp`, computed again when a file's time or size
    changes (``files``: name, mtime, size)."""
    digest = hashlib.sha256()
    for name, _, _ in files:
        digest.update(name.encode())
        digest.update(hashlib.sha256((folder / name).read_bytes()).digest())
    return digest.hexdigest()


def _stamped(locator: Any) -> Any:
    """``locator`` (a numba cache locator class) for the kernel's files only, stamped
    with :func:`kernels_source_stamp` instead of the one file's source."""

    class KernelLocator(locator):
        pporpe_kernels = True

        def get_source_stamp(self) -> str:
            return kernels_source_stamp()

        @classmethod
        def from_function(cls, py_func: Any, py_file: str) -> Any:
            if Path(py_file).resolve().parent != KERNELS_DIR:
                return None
            return super().from_function(py_func, py_file)

    KernelLocator.__name__ = KernelLocator.__qualname__ = f"Kernel{locator.__name__}"
    return KernelLocator


def _register_locators() -> None:
    """Put the kernel's locators first in numba's list (once per process), in numba's own
    order of preference."""
    if any(getattr(c, "pporpe_kernels", False) for c in CacheImpl._locator_classes):
        return
    bases = (UserProvidedCacheLocator, InTreeCacheLocator, UserWideCacheLocator)
    CacheImpl._locator_classes[:0] = [_stamped(b) for b in bases]


_register_locators()

scalar_jit = njit(cache=True, error_model="numpy")
"""Scalar code: numpy's error model (x / 0 is inf or nan, as in torch, never an exception)."""
loop_jit = njit(cache=True, fastmath=FM, error_model="numpy")
"""Loops: the same with :data:`FM` (they vectorise)."""
