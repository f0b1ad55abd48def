"""The one project exception type.

Every expected failure (bad input, missing stage output, misuse) raises `BoostNerfError` with a
single line that says what is wrong and what to do. The CLI turns it into that line on stderr and
exit code 2, with no traceback. Anything else is a bug and keeps its traceback.
"""


class BoostNerfError(Exception):
    """An expected, user-facing failure: one line, what is wrong and what to do."""

    exit_code = 2


class DataWarning(UserWarning):
    """Input that loads but may not mean what its author meant: one line, what and what to do. `load_scene` keeps
    them in `Scene.extra["warnings"]`; `pretrain` prints them."""


class BoxWarning(DataWarning):
    """A doubt about the scene box or near / far derived from the cameras; moot (dropped) when data.bbox gives the
    box."""


# what the allocators say when a tensor does not fit (CPU, CUDA, and sizes past what can be addressed)
_OUT_OF_MEMORY = ("can't allocate memory", "out of memory", "storage size calculation overflowed")


def out_of_memory(e: BaseException) -> bool:
    """True for an allocation that failed: MemoryError, torch.OutOfMemoryError (CUDA), or the RuntimeError with
    which the CPU allocator refuses a tensor. Such a failure is the settings' size, not a bug: the CLI says so in
    one line."""
    if isinstance(e, MemoryError):
        return True
    return isinstance(e, RuntimeError) and any(m in str(e).lower() for m in _OUT_OF_MEMORY)
