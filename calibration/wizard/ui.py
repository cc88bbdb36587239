"""How the wizard talks to a person: questionary prompts in a terminal, or fixed answers.

:class:`InteractiveUI` asks with questionary (arrow keys or the number shortcuts, Enter) and
prints with rich; Ctrl-C at a prompt stops the wizard (its progress is kept). :class:`AutoUI`
(``--yes``) takes every default answer and never waits, for scripts and CI.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from pathlib import Path

from rich.console import Console
from rich.table import Table

Choice = tuple[str, str]   # (key, label)


def _format(value) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)


class BaseUI(ABC):
    """Output shared by both kinds of UI."""

    interactive = False

    def __init__(self, console: Console | None = None):
        self.console = console or Console(highlight=False)

    def say(self, text: str) -> None:
        self.console.print(text)

    def heading(self, index: int, total: int, title: str) -> None:
        self.console.rule(f"[bold]step {index}/{total}: {title}")

    def show_result(self, title: str, metrics: dict, figures: Sequence[Path],
                    notes: Sequence[str] = ()) -> None:
        """Figures of merit as a table, notes, and where the pictures are."""
        table = Table(title=title, show_header=False, title_justify="left")
        for key, value in metrics.items():
            table.add_row(key, _format(value))
        self.console.print(table)
        for note in notes:
            self.console.print(f"  - {note}")
        for f in figures:
            self.console.print(f"  picture: {f}")

    # prompts (subclasses)
    @abstractmethod
    def choose(self, message: str, choices: Sequence[Choice], default: str) -> str:
        """The key of the chosen entry."""

    @abstractmethod
    def confirm(self, message: str, default: bool = True) -> bool:
        """Yes or no."""

    @abstractmethod
    def text(self, message: str, default: str = "",
             validate: Callable[[str], bool | str] | None = None) -> str:
        """A line of text (``validate`` returns True, or the message to show)."""

    @abstractmethod
    def wait(self, instruction: str) -> None:
        """Ask the person to do something and wait until they say it is done."""


class InteractiveUI(BaseUI):
    """questionary prompts (needs a terminal)."""

    interactive = True

    def choose(self, message: str, choices: Sequence[Choice], default: str) -> str:
        import questionary

        qc = [questionary.Choice(label, value=key) for key, label in choices]
        start = next(c for c in qc if c.value == default)
        return questionary.select(message, choices=qc, default=start,
                                  use_shortcuts=len(qc) <= 9).unsafe_ask()

    def confirm(self, message: str, default: bool = True) -> bool:
        import questionary

        return bool(questionary.confirm(message, default=default).unsafe_ask())

    def text(self, message: str, default: str = "",
             validate: Callable[[str], bool | str] | None = None) -> str:
        import questionary

        return questionary.text(message, default=default,
                                validate=validate or (lambda _: True)).unsafe_ask()

    def wait(self, instruction: str) -> None:
        import questionary

        self.console.print(f"[bold cyan]>>[/] {instruction}")
        questionary.press_any_key_to_continue("Press any key when done...").unsafe_ask()


class AutoUI(BaseUI):
    """Default answers, no waiting (``--yes``); every question is echoed with its answer."""

    def choose(self, message: str, choices: Sequence[Choice], default: str) -> str:
        label = dict(choices)[default]
        self.console.print(f"? {message} [dim](--yes)[/] {label}")
        return default

    def confirm(self, message: str, default: bool = True) -> bool:
        self.console.print(f"? {message} [dim](--yes)[/] {'yes' if default else 'no'}")
        return default

    def text(self, message: str, default: str = "",
             validate: Callable[[str], bool | str] | None = None) -> str:
        self.console.print(f"? {message} [dim](--yes)[/] {default}")
        return default

    def wait(self, instruction: str) -> None:
        self.console.print(f">> {instruction} [dim](--yes: going on)[/]")
