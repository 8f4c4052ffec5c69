"""Every option of every benchmark script says in --help what it does.

Each script's `main` builds its parser and parses; the parser is taken at that call, before anything runs, and its
options are read from argparse itself rather than from the help text's layout."""

from __future__ import annotations

import argparse

import pytest

from benchmark_helpers import BENCHMARKS, load_benchmark

SCRIPTS = sorted(p.stem for p in BENCHMARKS.glob("*.py"))


class Parsed(Exception):
    """Raised in place of parsing: the script's parser is in hand."""

    def __init__(self, parser: argparse.ArgumentParser):
        super().__init__(parser.prog)
        self.parser = parser


def script_parser(stem: str, monkeypatch) -> argparse.ArgumentParser:
    """The parser benchmarks/<stem>.py's main parses its command line with."""
    def caught(self, args=None, namespace=None):
        raise Parsed(self)

    bench = load_benchmark(stem)
    monkeypatch.setattr(argparse.ArgumentParser, "parse_args", caught)
    monkeypatch.setattr(argparse.ArgumentParser, "parse_known_args", caught)
    with pytest.raises(Parsed) as got:
        bench.main([])
    return got.value.parser


def options_without_help(parser: argparse.ArgumentParser) -> list[str]:
    """The options (and positionals) of `parser` and its subcommands whose help is empty; hidden ones (SUPPRESS)
    and --help itself are left out."""
    missing = []
    for action in parser._actions:
        if isinstance(action, argparse._HelpAction) or action.help == argparse.SUPPRESS:
            continue
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                missing += [f"{name} {option}" for option in options_without_help(sub)]
            continue
        if not (action.help or "").strip():
            missing.append("/".join(action.option_strings) or action.dest)
    return missing


def test_every_script_is_checked():
    assert {"error_vs_time", "live_recoarse", "metrics_speed"} <= set(SCRIPTS)


@pytest.mark.parametrize("stem", SCRIPTS)
def test_every_option_has_help(stem, monkeypatch):
    assert options_without_help(script_parser(stem, monkeypatch)) == [], f"benchmarks/{stem}.py"
