"""Small page pieces shared by the screens of the web app."""

from __future__ import annotations

from trame.widgets import html
from trame.widgets import vuetify3 as v3

__all__ = ["half_button", "heading"]


def heading(title: str, hint: str = "") -> None:
    """Show a screen's bold title with an optional one-paragraph hint below it."""
    html.Div(title, classes="text-subtitle-1 font-weight-bold mt-2")
    if hint:
        html.Div(hint, classes="text-body-2 text-medium-emphasis mb-1")


def half_button(label: str, **props) -> None:
    """Add a full-width button in a half-width column (two of them make a row of a panel)."""
    with v3.VCol(cols=6):
        v3.VBtn(label, block=True, **props)
