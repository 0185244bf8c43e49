"""Small page pieces shared by the screens of the web app."""

from __future__ import annotations

from trame.widgets import html

__all__ = ["heading"]


def heading(title: str, hint: str = "") -> None:
    """Show a screen's bold title with an optional one-paragraph hint below it."""
    html.Div(title, classes="text-subtitle-1 font-weight-bold mt-2")
    if hint:
        html.Div(hint, classes="text-body-2 text-medium-emphasis mb-1")
