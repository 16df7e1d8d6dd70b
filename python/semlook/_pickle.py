"""Pickle support: module-level callables that rebuild engine objects (pickle cannot name a
method of an extension type)."""


def rebuild_descriptors(arrays):
    from ._native import Descriptors

    return Descriptors.from_arrays(arrays)
