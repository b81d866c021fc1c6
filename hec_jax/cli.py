"""Command-line flags derived from the frozen config dataclasses (one definition, one default).

Every script describes what it runs with one frozen dataclass (its fields, nested configs
included, carry the defaults and the help text as comments or docstrings) and calls
:func:`parse` with a named preset as the default. Nested configs are flattened: a field
``learner.eta`` is the flag ``--eta`` (names are unique across a script's config tree; tyro
refuses duplicates).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TypeVar

import tyro

T = TypeVar("T")


def parse(default: T, argv: Sequence[str] | None = None, description: str | None = None) -> T:
    """Parses ``argv`` (default: ``sys.argv[1:]``) into a copy of ``default`` with flags applied.

    Args:
        default: a frozen dataclass instance: the preset whose fields are the defaults.
        argv: command-line arguments; None reads ``sys.argv``.
        description: the ``--help`` text (usually the script's docstring).

    Returns:
        An instance of ``type(default)``; its ``__post_init__`` checks run on the result, so
        invalid values end in a one-line error before anything is compiled.
    """
    return tyro.cli(
        type(default),
        default=default,
        args=argv,
        description=description,
        config=(tyro.conf.OmitArgPrefixes,),
    )
