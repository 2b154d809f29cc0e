"""Helpers that several compiled kernels share (:func:`sylva.core.jit.helper`): one implementation each,
compiled into every kernel that calls it, and tested against its Python form (tests/test_kernels.py)."""
