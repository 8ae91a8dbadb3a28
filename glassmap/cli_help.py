"""Help text of the ``glassmap`` command tree: each option's default is said once."""

from __future__ import annotations

import argparse


class DefaultsHelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Appends ``(default: X)`` to an option's help unless the help already says its default; says nothing
    of a default that means nothing (None, False: an unset option or an off switch)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if action.default is None or action.default is False:  # "(default: None)" says nothing
            return text.replace(" (default: %(default)s)", "")
        if "default" in text:
            return text
        return super()._get_help_string(action)


def tidy_help(parser: argparse.ArgumentParser) -> None:
    """Use :class:`DefaultsHelpFormatter` in every (sub)parser of the tree that adds defaults to its help;
    drop ``(default: %(default)s)`` where the default is None or False."""
    if parser.formatter_class is argparse.ArgumentDefaultsHelpFormatter:
        parser.formatter_class = DefaultsHelpFormatter
    for action in parser._actions:
        if action.help and (action.default is None or action.default is False):
            action.help = action.help.replace(" (default: %(default)s)", "")  # says nothing
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                tidy_help(sub)
