"""One toolkit: `rafd COMMAND` reaches every tool (rafd.cli.main.COMMANDS, and other packages' "rafd.commands" entry
points), the command table and the version are written once, the shared flags
mean one thing everywhere (rafd.cli.flags), every flag has help, usage lines are argparse's own, no old
spelling is kept, and docs/cli.md lists every command and the shared flags as the parsers have them."""

from __future__ import annotations

import argparse
import importlib
import re
import sys
from importlib import metadata
from pathlib import Path

import pytest

from rafd.cli import flags
from rafd.cli import main as dispatcher
from rafd.cli.main import COMMANDS

REPO = Path(__file__).resolve().parents[3]
TYPED = {c.name: c.name.replace("-", " ", 1) if c.name.startswith("bench-") else c.name for c in COMMANDS}
GROUPED = {c.name for c in COMMANDS if c.name.startswith("bench-")}  # `rafd bench NAME` only: no rafd-* alias
# rafd, an alias per command outside a group (issue 57: what is installed is what users run)
MAX_SCRIPTS = 16


def parser_of(command: str) -> argparse.ArgumentParser:
    """The command's parser, built as `rafd COMMAND` builds it."""
    target = next(c.target for c in COMMANDS if c.name == command)
    module = importlib.import_module(target.split(":")[0])
    build = getattr(module, "build_parser", None) or module._parser
    flags.set_dispatched(True)
    try:
        return build()
    finally:
        flags.set_dispatched(False)


def all_parsers(command: str) -> list[argparse.ArgumentParser]:
    """The parser and its sub-commands' parsers."""
    out, todo = [], [parser_of(command)]
    while todo:
        parser = todo.pop()
        out.append(parser)
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                todo += list(action.choices.values())
    return out


def options_of(command: str) -> set[str]:
    return {option for parser in all_parsers(command) for action in parser._actions for option in action.option_strings}


def pyproject() -> dict:
    tomllib = pytest.importorskip("tomllib", reason="tomllib needs Python 3.11")
    return tomllib.loads((REPO / "pyproject.toml").read_text())


# ----------------------------------------------------------------------------- the one command
def test_the_command_table_is_written_once_and_every_alias_runs_the_same_function():
    """rafd.cli.main.COMMANDS is the one table; pyproject.toml holds only what packaging needs: the `rafd` script and
    each command's `rafd-NAME` alias (none for `rafd bench NAME`), running what `rafd NAME` runs, and nothing else."""
    project = pyproject()["project"]
    assert "rafd.commands" not in project.get("entry-points", {})  # not a second table
    scripts = dict(project["scripts"])
    assert scripts.pop("rafd") == "rafd.cli.main:main"
    for command in COMMANDS:
        alias = scripts.pop(f"rafd-{command.name}", None)
        assert alias == (None if command.name in GROUPED else command.target), command.name
    assert not scripts, f"scripts that run no command of the table: {sorted(scripts)}"
    assert len(project["scripts"]) <= MAX_SCRIPTS


def test_the_version_is_written_once():
    """rafd.__version__ is the version; pyproject.toml reads it (dynamic) instead of writing it again."""
    import rafd

    config = pyproject()
    assert "version" not in config["project"] and "version" in config["project"]["dynamic"]
    assert config["tool"]["setuptools"]["dynamic"]["version"] == {"attr": "rafd.__version__"}
    assert re.fullmatch(r"\d+\.\d+\.\d+", rafd.__version__)


def test_rafd_version_prints_the_package_version(capsys):
    import rafd

    assert dispatcher.main(["--version"]) == 0
    assert capsys.readouterr().out == f"rafd {rafd.__version__}\n"


def test_rafd_help_lists_every_command(capsys):
    assert dispatcher.main(["--help"]) == 0
    listed = capsys.readouterr().out
    for command in COMMANDS:
        assert re.search(rf"^  {TYPED[command.name]} +{re.escape(command.summary)}$", listed, re.M), command.name
    assert dispatcher.main([]) == 2 and "commands:" in capsys.readouterr().err  # no command: the list, exit 2


@pytest.mark.parametrize("command", [c.name for c in COMMANDS])
def test_rafd_command_help_reaches_the_tool(command, capsys):
    with pytest.raises(SystemExit) as exit_info:
        dispatcher.main([*TYPED[command].split(), "--help"])
    assert exit_info.value.code == 0
    help_text = capsys.readouterr().out
    assert help_text.startswith(f"usage: rafd {TYPED[command]}"), help_text[:200]


def test_commands_are_found_through_the_installed_entry_points(monkeypatch, capsys):
    """The dispatcher reads the entry points, importing a command only when it runs: a command another package
    declares is listed and run like the built-in ones (an installation that still declares the built-in ones, as
    before the table was written once, changes nothing)."""
    installed = [metadata.EntryPoint(c.name, c.target, dispatcher.GROUP) for c in COMMANDS]
    plugin = metadata.EntryPoint("hello", "tests.rafd.cli.test_toolkit:hello_command", dispatcher.GROUP)
    monkeypatch.setattr(
        metadata, "entry_points", lambda group: [*installed, plugin] if group == dispatcher.GROUP else []
    )
    assert "tests.rafd.cli.test_toolkit" in sys.modules
    assert dispatcher.main(["--help"]) == 0
    listed = capsys.readouterr().out
    assert "  hello " in listed and "  serve " in listed
    assert dispatcher.main(["hello", "a", "b"]) == 7
    assert capsys.readouterr().out == "hello ['a', 'b']\n"


def test_every_command_runs_without_entry_points(monkeypatch, capsys):
    """A fresh install declares no "rafd.commands" entry point: the table alone lists and runs the commands."""
    monkeypatch.setattr(metadata, "entry_points", lambda group: [])
    assert dispatcher.installed_commands() == {c.name: c.target for c in COMMANDS}
    assert dispatcher.main(["--help"]) == 0
    listed = capsys.readouterr().out
    assert all(f"\n  {TYPED[c.name]} " in listed for c in COMMANDS)


def hello_command(argv):
    print("hello", list(argv))
    return 7


def test_an_unknown_command_is_refused_with_a_suggestion(capsys):
    assert dispatcher.main(["serv"]) == 2
    assert "did you mean `rafd serve`" in capsys.readouterr().err
    assert dispatcher.main(["bench", "sped"]) == 2
    assert "did you mean `rafd bench speed`" in capsys.readouterr().err
    assert dispatcher.main(["bench"]) == 2 and "speed" in capsys.readouterr().err


def test_the_rafd_prefixed_aliases_keep_their_program_name(capsys):
    from rafd.cli.prepare import build_parser

    assert build_parser().prog == "rafd-prepare"
    assert parser_of("prepare").prog == "rafd prepare"


# ----------------------------------------------------------------------------- flags
@pytest.mark.parametrize("command", [c.name for c in COMMANDS])
def test_every_flag_has_help_and_usage_is_argparses_own(command):
    for parser in all_parsers(command):
        for action in parser._actions:
            if isinstance(action, (argparse._HelpAction, argparse._SubParsersAction)):
                continue
            assert action.help and action.help.strip(), f"{parser.prog} {action.option_strings or action.dest}"
        for text in (parser.description or "", parser.epilog or ""):
            for line in text.splitlines():  # no hand-made usage block: a line showing a command and its flags
                assert not re.match(r"^\s*rafd[- ][a-z-]+ .*\[--", line), f"{parser.prog}: {line}"


SHARED_OUTPUTS = {  # command -> what its --out writes
    "train": "CKPT",
    "simulate": "DIR|PNG",
    "odometry": "CSV",
    "prepare": "CACHE",
    "polar": "DIR",
    "client": "DIR",
    "export": "MODEL.onnx",
}


def test_the_shared_vocabulary_holds_in_every_command():
    for command, metavar in SHARED_OUTPUTS.items():
        out = next(a for a in parser_of(command)._actions if "--out" in a.option_strings)
        assert out.metavar == metavar, command
    for command in (c.name for c in COMMANDS):
        options = options_of(command)
        # the old, ambiguous spellings are gone
        for old in ("--frames", "--num-workers", "--size", "--crop", "--no-progress", "--data", "--gate-frames"):
            assert old not in options, f"rafd {TYPED[command]} still has {old} as a flag of its own"
        for parser in all_parsers(command):
            for action in parser._actions:
                if "--split" in action.option_strings or "--val-split" in action.option_strings:
                    assert isinstance(action, argparse._AppendAction), f"{parser.prog}: --split must be repeatable"
                if "--resume" in action.option_strings:
                    assert action.nargs == 0, f"{parser.prog}: --resume takes no value"
    long_running = {c.name for c in COMMANDS} - {"serve"}
    for command in long_running:
        assert "--quiet" in options_of(command), command


def run_parse(module: str, function: str, argv: list[str]) -> argparse.Namespace:
    return getattr(importlib.import_module(module), function)(argv)


def test_the_export_output_is_positional_or_out_once(capsys):
    from export.cli import main

    with pytest.raises(SystemExit):
        main(["ck.pt"])
    assert "OUTPUT.onnx or --out" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["ck.pt", "a.onnx", "--out", "b.onnx"])
    assert "once" in capsys.readouterr().err


def test_simulate_deals_sequences_to_repeated_splits(tmp_path):
    import json

    from rafd.cli.simulate import main

    out = tmp_path / "sim"
    argv = ["--out", str(out), "--sequences", "3", "--sequence-frames", "1", "--scan-size", "64", "--quiet"]
    assert main([*argv, "--split", "train", "--split", "test"]) == 0
    splits = [json.loads((out / f"sim_0_{k}" / "meta.json").read_text())["set"] for k in range(3)]
    assert splits == ["train", "test", "train"]


# ----------------------------------------------------------------------------- the docs' CLI page
def cli_page() -> str:
    return (REPO / "docs" / "cli.md").read_text()


def test_the_cli_page_lists_every_command():
    page = cli_page()
    for command in COMMANDS:
        assert f"`rafd {TYPED[command.name]}`" in page, command.name
        if command.name not in GROUPED:
            assert f"`rafd-{command.name}`" in page, command.name


def test_the_shared_flags_table_matches_the_parsers():
    """Each row: `| `--flag` | meaning | commands |`; every command named takes the flag, and every command that
    takes the flag is named."""
    section = cli_page().split("## Shared flags", 1)[1].split("\n## ", 1)[0]
    rows = [line for line in section.splitlines() if line.startswith("| `--")]
    assert len(rows) >= 12
    for row in rows:
        cells = [cell.strip() for cell in row.strip("|").split("|")]
        flag = re.match(r"`(--[a-z-]+)", cells[0]).group(1)
        named = set(re.findall(r"`rafd ([a-z0-9 -]+?)`", cells[2]))
        takes = {TYPED[c.name] for c in COMMANDS if flag in options_of(c.name)}
        assert named == takes, f"{flag}: the table says {sorted(named)}, the parsers {sorted(takes)}"


# ----------------------------------------------------------------------------- progress
def test_progress_is_silent_with_quiet_and_throttled_off_a_terminal(capsys, monkeypatch):
    from rafd import progress

    monkeypatch.setattr(progress, "_quiet", False)
    for _ in progress.track(range(20000), desc="a long stage", unit="it"):
        pass
    err = capsys.readouterr().err
    lines = [line for line in re.split(r"[\r\n]+", err) if line.strip()]
    assert 1 <= len(lines) <= 3 and "a long stage" in lines[-1] and "20000/20000" in lines[-1]  # not 20000 lines
    progress.set_quiet(True)
    try:
        for _ in progress.track(range(100), desc="quiet"):
            pass
        progress.stage("a stage")
        with progress.Stages("job", 2) as stages:
            stages.begin("one")
            stages.begin("two")
    finally:
        progress.set_quiet(False)
    assert capsys.readouterr().err == ""


def test_stages_say_what_runs_and_how_far(capsys):
    from rafd import progress

    with progress.Stages("bench speed", 3) as stages:
        stages.begin("export")
        stages.begin("time the steps")
        stages.begin("gate")
    err = capsys.readouterr().err
    assert "bench speed: gate" in err and "3/3" in err


# ----------------------------------------------------------------------------- the front page
def readme_section(title: str) -> str:
    return (REPO / "README.md").read_text().split(f"\n## {title}\n", 1)[1].split("\n## ", 1)[0]


def test_the_front_page_lists_every_command():
    """README's command list names every command (`rafd bench speed | accuracy | ...` names a group's members)."""
    listed = readme_section("Command-line tools")
    named = set(re.findall(r"^- `rafd ([a-z]+)", listed, re.M))
    groups = {g: re.search(rf"^- `rafd {g} ([a-z0-9 |-]+)`", listed, re.M) for g in dispatcher.GROUPS}
    for command in COMMANDS:
        group, _, member = command.name.partition("-")
        if group in groups and member:
            assert groups[group] and member in groups[group].group(1).split(" | "), command.name
        else:
            assert command.name in named, command.name


def test_the_front_page_links_every_page_of_the_site():
    yaml = pytest.importorskip("yaml")
    config = yaml.safe_load((REPO / "mkdocs.yml").read_text().replace("!!python/name:", ""))
    pages = [next(iter(item.values())) for item in config["nav"]]
    table = readme_section("Documentation")
    for page in pages:
        assert f"](docs/{page})" in table, page
