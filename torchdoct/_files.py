"""The former name of :mod:`torchdoct.files` (the same functions), kept while a few modules still import
it from here; new code imports :mod:`torchdoct.files`."""

from __future__ import annotations

from .files import *  # noqa: F401,F403
from .files import __all__  # noqa: F401
