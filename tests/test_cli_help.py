"""Every ``glassmap`` command and sub-command prints its --help (argparse formats help strings lazily, so a
stray '%' in one only fails when that help is printed)."""

from __future__ import annotations

import argparse

import pytest

from runtime.cli import build_parser


def _parsers(parser: argparse.ArgumentParser, path: tuple[str, ...] = ()):
    yield path, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _parsers(sub, (*path, name))


def test_every_help_formats():
    seen = []
    for path, parser in _parsers(build_parser()):
        text = parser.format_help()
        assert "usage:" in text, path
        seen.append(" ".join(path))
    assert {"demo", "run", "replay", "bench", "recover", "pose eval", "sim bench", "glass experiment", "glass bench",
            "hokuyo bench", "pioneer bench"} <= set(seen)


@pytest.mark.parametrize("argv", [["--help"], ["demo", "--help"]])
def test_help_exits_zero(argv, capsys):
    with pytest.raises(SystemExit) as e:
        build_parser().parse_args(argv)
    assert e.value.code == 0
    assert "usage:" in capsys.readouterr().out


def test_every_option_has_help_and_says_its_default_once():
    problems = []
    for path, parser in _parsers(build_parser()):
        fmt = parser._get_formatter()
        for action in parser._actions:
            if isinstance(action, (argparse._SubParsersAction, argparse._HelpAction)):
                continue
            where = f"glassmap {' '.join(path)} {'/'.join(action.option_strings) or action.dest}"
            if not action.help:
                problems.append(f"{where}: no help")
                continue
            text = fmt._expand_help(action)
            if text.count("(default") > 1 or "(default: None)" in text:
                problems.append(f"{where}: {text}")
    assert not problems, "\n".join(problems)
