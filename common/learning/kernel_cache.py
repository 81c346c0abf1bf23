"""numba's cache of the compiled backend's kernels, filled afresh: ``make setup``, the image
build and ``make bench-scale`` run ``python -m fedhpg.common.learning.kernel_cache``.

numba keys a kernel's cache by its own file alone: a kernel in ``fused.py`` loaded from the
cache keeps the code it was compiled with of the kernels it calls in ``kernels.py``, even after
that file changed. So whoever fills the cache empties it first (:func:`forget_compiled`); the
Makefile does so whenever a kernel's source is newer than its last fill.
"""

from __future__ import annotations

from fedhpg.common.learning.batched import estimator, fused, kernels
from fedhpg.common.learning.batched.backend import warm_up
from fedhpg.envs import compiled as environment


def forget_compiled() -> int:
    """Empty numba's cache of every kernel of the compiled backend; returns how many kernels."""
    dispatchers = [
        value
        for module in (kernels, fused, estimator, environment)
        for value in vars(module).values()
        if hasattr(value, "_cache") and hasattr(value, "py_func")  # a numba kernel
    ]
    for dispatcher in dispatchers:
        dispatcher._cache.flush()
    return len(dispatchers)


if __name__ == "__main__":
    forget_compiled()
    print(f"compiled backend ready ({warm_up():.1f} s)")
