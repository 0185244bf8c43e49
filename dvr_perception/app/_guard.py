"""The guard every page handler of the web app wears: errors go to the page, not the log."""

from __future__ import annotations

import functools
import logging
import warnings

from dvr_perception.errors import DVRInputError

__all__ = ["guard"]

log = logging.getLogger("dvr_perception.app")


def guard(fn):
    """Show input errors (and unexpected ones) in the page instead of failing the handler."""

    @functools.wraps(fn)
    def wrapper(self, *args, **kwargs):
        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                out = fn(self, *args, **kwargs)
            if caught:
                self.state.info = "; ".join(str(w.message) for w in caught[:3])
            return out
        except (DVRInputError, OSError, ValueError) as exc:
            self.fail(str(exc))
        except Exception as exc:
            log.exception("unexpected error in %s", fn.__name__)
            self.fail(f"unexpected {type(exc).__name__}: {exc}")
        return None

    return wrapper
