"""Errors the library raises for problems a user can fix; the CLI prints them on one line.

`InputError` (from `matching.errors`) names an unusable input file; `UserError` an unusable
option or output folder. Neither is a bug, so neither ever shows a traceback.
"""

from __future__ import annotations

from matching.errors import InputError


class UserError(Exception):
    """A problem the user can fix (bad arguments, refused output folder); printed on one line."""


USER_ERRORS: tuple[type[Exception], ...] = (InputError, UserError)

__all__ = ["InputError", "USER_ERRORS", "UserError"]
