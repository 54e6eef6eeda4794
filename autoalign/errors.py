"""User-facing errors: one line that names the file and the fix."""

from __future__ import annotations


class AutoalignError(Exception):
    """A mistake in the user's input. The CLI prints it as one line and exits with code 2.

    The message should name the offending file (or option) and say how to fix it.
    """


class BackendError(AutoalignError):
    """The rendering backend (drjit/mitsuba LLVM) cannot start on this machine."""
