"""Deprecated names kept for one release: a warning, then the new name's behaviour.

The public API spells "colour" (British, as the rest of the project); names and keywords
spelt "color" keep working for one release with a :class:`DeprecationWarning`.
"""

from __future__ import annotations

import functools
import warnings

__all__ = ["deprecated_alias", "renamed_keyword"]


def deprecated_alias(new, old_name: str, new_path: str):
    """Return a function ``old_name`` that warns, then calls ``new`` (``new_path`` in the text).

    Examples
    --------
    >>> def twice(x):
    ...     return 2 * x
    >>> old = deprecated_alias(twice, "double", "mod.twice")
    >>> import warnings
    >>> with warnings.catch_warnings(record=True) as caught:
    ...     warnings.simplefilter("always")
    ...     old(3), str(caught[0].message)
    (6, 'double is deprecated; use mod.twice')
    """

    @functools.wraps(new)
    def alias(*args, **kwargs):
        warnings.warn(f"{old_name} is deprecated; use {new_path}", DeprecationWarning, stacklevel=2)
        return new(*args, **kwargs)

    alias.__name__ = alias.__qualname__ = old_name.rpartition(".")[2]
    alias.__doc__ = f"Deprecated alias of :func:`{new_path}`."
    return alias


def renamed_keyword(old: str, new: str, *, name: str | None = None):
    """Decorate a function whose keyword ``old`` is now ``new``: ``old=`` warns and is passed on.

    Giving both is a :class:`TypeError`, as any repeated argument.  ``name`` is the callable's
    name in the messages (default: the function's ``__name__``; e.g. the class for ``__init__``).

    Examples
    --------
    >>> @renamed_keyword("colors", "colours")
    ... def paint(*, colours=None):
    ...     return colours
    >>> import warnings
    >>> with warnings.catch_warnings(record=True) as caught:
    ...     warnings.simplefilter("always")
    ...     paint(colors=[1]), paint(colours=[2]), len(caught)
    ([1], [2], 1)
    """

    def decorate(fn):
        shown = name or fn.__name__

        @functools.wraps(fn)
        def wrapper(*args, **kwargs):
            if old in kwargs:
                if new in kwargs:
                    raise TypeError(f"{shown}() got both {old}= and {new}= (use {new}=)")
                warnings.warn(
                    f"{shown}({old}=...) is deprecated; use {new}=",
                    DeprecationWarning,
                    stacklevel=2,
                )
                kwargs[new] = kwargs.pop(old)
            return fn(*args, **kwargs)

        return wrapper

    return decorate
