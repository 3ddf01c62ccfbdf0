"""The one error type users can cause, and its exit codes.

Exit codes (spec): 2 bad input or usage, 3 the data do not allow a safe answer.
"""

from __future__ import annotations

EXIT_BAD_INPUT = 2
EXIT_NO_SAFE_ANSWER = 3


class EMRegError(Exception):
    """A problem with the user's input: the message names the input and says what to do."""

    exit_code: int = EXIT_BAD_INPUT

    def __init__(self, message: str, exit_code: int | None = None) -> None:
        super().__init__(message)
        if exit_code is not None:
            self.exit_code = exit_code


class NoSafeAnswerError(EMRegError):
    """The data were read, but they do not allow a safe answer (ambiguous pairing, too few markers...)."""

    exit_code = EXIT_NO_SAFE_ANSWER

