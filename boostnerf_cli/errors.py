"""The one project exception type.

Every expected failure (bad input, missing stage output, misuse) raises `BoostNerfError` with a
single line that says what is wrong and what to do. The CLI turns it into that line on stderr and
exit code 2, with no traceback. Anything else is a bug and keeps its traceback.
"""


class BoostNerfError(Exception):
    """An expected, user-facing failure: one line, what is wrong and what to do."""

    exit_code = 2
