"""Fault injection for the tests: a command that kills itself at a known point, so the resume and atomic-write tests
(tests/test_resume.py, tests/test_cli_moe.py) stop the CLI where they mean to instead of at timed moments.

Inert unless `BOOSTNERF_TEST_KILL` is set when a command starts (`install`, called once by `cli.main`):

    checkpoint:N   SIGKILL right after the N-th training checkpoint of the process is written
    write:NAME     SIGKILL inside the atomic write of the file NAME: the temporary file complete and flushed, before
                   its rename over NAME (`workspace.atomic_path`)

Nothing in the write path knows of it: `install` wraps `train.TrainCheckpoint.save` and the rename.
"""

from __future__ import annotations

import itertools
import os
import signal
from collections.abc import Mapping
from pathlib import Path

from boostnerf_cli.errors import BoostNerfError

ENV = "BOOSTNERF_TEST_KILL"


def install(environ: Mapping[str, str] = os.environ) -> None:
    """Arm the kill point `environ[ENV]` names, if any."""
    spec = environ.get(ENV)
    if not spec:
        return
    kind, _, arg = spec.partition(":")
    if kind == "checkpoint" and arg.isdigit():
        _after_checkpoint(int(arg))
    elif kind == "write" and arg:
        _before_rename(arg)
    else:
        raise BoostNerfError(f"{ENV}={spec!r}: give checkpoint:N or write:NAME (a test's kill point)")


def _die() -> None:
    os.kill(os.getpid(), signal.SIGKILL)


def _after_checkpoint(n: int) -> None:
    from boostnerf_cli.train import TrainCheckpoint

    save, written = TrainCheckpoint.save, itertools.count(1)

    def save_then_maybe_die(self, *args, **kwargs) -> None:
        save(self, *args, **kwargs)
        if next(written) == n:
            _die()

    TrainCheckpoint.save = save_then_maybe_die


def _before_rename(name: str) -> None:
    replace = os.replace

    def replace_or_die(src, dst, *args, **kwargs):
        if Path(dst).name == name:
            _die()
        return replace(src, dst, *args, **kwargs)

    os.replace = replace_or_die
