"""Values computed from one rows array, kept while that array lives.

The engine evaluates the same terms on the same rows many times: every candidate of a target shares most of
its terms with the others, and each is evaluated on the fit rows, the pick rows and the rows moved for its
self-feedback (identification.self_feedback). A term's column is computed once per rows array and reused.
Entries are keyed by the array object (not its content) and dropped when it is garbage collected; the rows
arrays the engine evaluates on are never modified in place once made, which is what makes this safe.
"""

from __future__ import annotations

import weakref
from collections.abc import Callable, Hashable

import numpy as np

# bytes kept per rows array: the 250 Hz closed-loop flight's 15,000 rows hold 125 kB per column, so about
# 1600 columns; past it values are computed and not kept
MAX_BYTES_PER_ARRAY = 200 * 2**20

_stores: dict[int, tuple[weakref.ref, dict[Hashable, np.ndarray], list[int]]] = {}


def cached(X: np.ndarray, key: Hashable, compute: Callable[[], np.ndarray]) -> np.ndarray:
    """compute()'s value for the rows X under key, computed once while X lives (read-only: shared)."""
    entry = _stores.get(id(X))
    if entry is None or entry[0]() is not X:
        try:
            ref = weakref.ref(X)
        except TypeError:  # not weak-referenceable: nothing to key on
            return compute()
        entry = (ref, {}, [0])
        _stores[id(X)] = entry
        weakref.finalize(X, _stores.pop, id(X), None)
    store, used = entry[1], entry[2]
    value = store.get(key)
    if value is None:
        value = compute()
        if isinstance(value, np.ndarray) and used[0] + value.nbytes <= MAX_BYTES_PER_ARRAY:
            value.flags.writeable = False
            store[key] = value
            used[0] += value.nbytes
    return value
