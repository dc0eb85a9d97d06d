"""Counting NumPy's array-memory allocations: a data-memory handler (NEP 49) that counts and forwards to libc.

NumPy allocates every array's data through the current handler (a context variable); ``tracemalloc`` sees those
allocations but mixes them with the interpreter's small objects, and its peak cannot tell a 24-byte temporary
from a frame. Installed with :func:`counting`, this handler counts each malloc, calloc and realloc of array data
in the current thread. The handler is set through NumPy's C API table (``PyDataMem_SetHandler``/``GetHandler``);
:func:`counting` checks that the table entries are what it expects and fails loudly otherwise.
"""
from __future__ import annotations

import contextlib
import ctypes

import numpy as np

_MALLOC = ctypes.CFUNCTYPE(ctypes.c_void_p, ctypes.c_void_p, ctypes.c_size_t)
_CALLOC = ctypes.CFUNCTYPE(ctypes.c_void_p, ctypes.c_void_p, ctypes.c_size_t, ctypes.c_size_t)
_REALLOC = ctypes.CFUNCTYPE(ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_size_t)
_FREE = ctypes.CFUNCTYPE(None, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_size_t)


class _Allocator(ctypes.Structure):
    _fields_ = [("ctx", ctypes.c_void_p), ("malloc", _MALLOC), ("calloc", _CALLOC), ("realloc", _REALLOC),
                ("free", _FREE)]


class _Handler(ctypes.Structure):  # PyDataMem_Handler (numpy/core/include/numpy/ndarraytypes.h)
    _fields_ = [("name", ctypes.c_char * 127), ("version", ctypes.c_uint8), ("allocator", _Allocator)]


_libc = ctypes.CDLL(None)
_libc.malloc.restype, _libc.malloc.argtypes = ctypes.c_void_p, [ctypes.c_size_t]
_libc.calloc.restype, _libc.calloc.argtypes = ctypes.c_void_p, [ctypes.c_size_t, ctypes.c_size_t]
_libc.realloc.restype, _libc.realloc.argtypes = ctypes.c_void_p, [ctypes.c_void_p, ctypes.c_size_t]
_libc.free.argtypes = [ctypes.c_void_p]

COUNT = [0]


def _m(ctx, n):
    COUNT[0] += 1
    return _libc.malloc(n)


def _c(ctx, a, b):
    COUNT[0] += 1
    return _libc.calloc(a, b)


def _r(ctx, p, n):
    COUNT[0] += 1
    return _libc.realloc(p, n)


def _f(ctx, p, n):
    _libc.free(p)


# module-level: arrays made under the handler keep its capsule, and free through it, for as long as they live
_CALLBACKS = (_MALLOC(_m), _CALLOC(_c), _REALLOC(_r), _FREE(_f))
_HANDLER = _Handler(b"sonicverse_counting", 1, _Allocator(None, *_CALLBACKS))
_NAME = ctypes.create_string_buffer(b"mem_handler")
_new_capsule = ctypes.pythonapi.PyCapsule_New
_new_capsule.restype, _new_capsule.argtypes = ctypes.py_object, [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p]
_CAPSULE = _new_capsule(ctypes.addressof(_HANDLER), ctypes.addressof(_NAME), None)


def _api():
    get = ctypes.pythonapi.PyCapsule_GetPointer
    get.restype, get.argtypes = ctypes.c_void_p, [ctypes.py_object, ctypes.c_char_p]
    table = ctypes.cast(get(np.core.multiarray._ARRAY_API, None), ctypes.POINTER(ctypes.c_void_p))
    set_handler = ctypes.PYFUNCTYPE(ctypes.py_object, ctypes.py_object)(table[304])
    get_handler = ctypes.PYFUNCTYPE(ctypes.py_object)(table[305])
    return set_handler, get_handler


@contextlib.contextmanager
def counting():
    """Within the block, NumPy allocates array data through the counting handler; yields a function returning
    how many allocations it has counted so far."""
    set_handler, get_handler = _api()
    if np.core.multiarray.get_handler_name() != "default_allocator":
        raise RuntimeError(f"unexpected NumPy memory handler {np.core.multiarray.get_handler_name()}")
    old = set_handler(_CAPSULE)
    try:
        if np.core.multiarray.get_handler_name() != "sonicverse_counting" or get_handler() is not _CAPSULE:
            raise RuntimeError("NumPy's C API table is not laid out as expected (PyDataMem_SetHandler)")
        start = COUNT[0]
        yield lambda: COUNT[0] - start
    finally:
        set_handler(old)
