"""User documentation: every ``--help`` renders cleanly, the docs' links resolve, every command
and every ``diagnose --json`` key is documented."""
from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from streamcal.cli import build_parser, main
from streamcal.model.catalog import EFFECT_NAMES

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
#: Internal references and reStructuredText/Sphinx markup a user must not see in --help.
FORBIDDEN = ("SPEC", "../shared", "``", ":class:", ":func:", ":mod:", ":data:")


def _commands() -> list[str]:
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    return sorted(sub.choices)


def _help(argv: list[str], capsys) -> str:
    with pytest.raises(SystemExit) as exc:
        main(argv + ["--help"])
    assert exc.value.code == 0
    return capsys.readouterr().out


def test_the_parser_has_the_commands_the_docs_describe():
    assert {"demo", "fit", "diagnose", "report", "convert", "export", "apply", "batch",
            "replay", "daemon", "serial", "record"} <= set(_commands())


@pytest.mark.parametrize("command", [None] + _commands())
def test_help_renders_without_internal_references_or_markup(command, capsys):
    out = _help([] if command is None else [command], capsys)
    assert out.startswith("usage: streamcal")
    for bad in FORBIDDEN:
        assert bad not in out, f"{command or 'streamcal'} --help shows {bad!r}"


@pytest.mark.parametrize("command", _commands())
def test_every_command_help_has_a_description(command, capsys):
    out = _help([command], capsys)
    # argparse prints the description between the usage block and the first argument group
    head = out.split("\n\n")
    assert len(head) > 2 and not head[1].lstrip().startswith(("positional arguments:", "options:")), \
        f"{command} --help has no description"


def test_fit_help_names_every_effect(capsys):
    out = " ".join(_help(["fit"], capsys).split())   # argparse wraps lines anywhere
    for name in EFFECT_NAMES:
        assert name in out, f"fit --help does not name {name}"


def _markdown_files() -> list[Path]:
    return [ROOT / "README.md"] + sorted(DOCS.glob("*.md"))


def test_the_docs_exist():
    for name in ("README.md", "tracks_and_inputs.md", "calibration_file.md", "effects.md",
                 "diagnosis.md", "cli.md", "python_api.md"):
        assert (DOCS / name).is_file(), name


@pytest.mark.parametrize("path", _markdown_files(), ids=lambda p: p.name)
def test_relative_links_point_to_files_that_exist(path):
    text = path.read_text(encoding="utf-8")
    links = re.findall(r"\]\(([^)\s]+)\)", text)
    for link in links:
        if re.match(r"[a-z]+:", link) or link.startswith("#"):
            continue
        target = (path.parent / link.split("#", 1)[0]).resolve()
        assert target.exists(), f"{path.name}: link {link!r} points to a missing file"


@pytest.mark.parametrize("path", _markdown_files(), ids=lambda p: p.name)
def test_docs_do_not_cite_the_internal_spec(path):
    text = path.read_text(encoding="utf-8")
    assert "SPEC" not in text and "../shared" not in text


def test_every_command_is_in_cli_md():
    text = (DOCS / "cli.md").read_text(encoding="utf-8")
    for command in _commands():
        assert re.search(rf"^## {re.escape(command)}$", text, re.M), \
            f"docs/cli.md has no section for {command}"


def test_every_effect_is_in_effects_md():
    text = (DOCS / "effects.md").read_text(encoding="utf-8")
    for name in EFFECT_NAMES:
        assert re.search(rf"^## {name}$", text, re.M), f"docs/effects.md has no section {name}"


#: Objects whose keys are data (column or effect names), not names the docs can list.
_DATA_KEYED = {"covariates", "candidate_baselines", "by"}


def _keys(value, parent: str | None = None, out: set | None = None) -> set:
    out = set() if out is None else out
    if isinstance(value, dict):
        for key, child in value.items():
            if parent not in _DATA_KEYED:
                out.add(key)
            _keys(child, key, out)
    elif isinstance(value, list):
        for child in value:
            _keys(child, parent, out)
    return out


@pytest.mark.slow
def test_every_diagnose_json_key_is_documented(tmp_path, capsys):
    from streamcal.sim import simulate

    path = tmp_path / "sim.csv.gz"
    simulate(60.0, seed=1).track.write(path)
    assert main(["diagnose", str(path), "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    keys = _keys(result)
    assert {"verdict", "candidates", "misfit", "ladder", "noise"} <= keys
    text = (DOCS / "diagnosis.md").read_text(encoding="utf-8")
    undocumented = sorted(k for k in keys if f"`{k}`" not in text)
    assert not undocumented, f"docs/diagnosis.md does not mention {undocumented}"


@pytest.mark.parametrize("path", _markdown_files(), ids=lambda p: p.name)
def test_table_rows_have_as_many_cells_as_the_header(path):
    """A '|' inside a cell (e.g. |B| in code) splits it and breaks the rendered table."""
    rows = None
    for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        if not line.startswith("|"):
            rows = None
            continue
        cells = len(re.findall(r"(?<!\\)\|", line)) - 1
        if rows is None:
            rows = cells
        assert cells == rows, f"{path.name}:{number}: {cells} cells, the header has {rows}"


def _sections() -> dict[str, str]:
    """docs/cli.md cut at its ``## `` headings: heading → text."""
    text = (DOCS / "cli.md").read_text(encoding="utf-8")
    parts = re.split(r"^## +(.+)$", text, flags=re.M)
    return {head.strip(): body for head, body in zip(parts[1::2], parts[2::2])}


#: An option as docs write it in code: ``--alt-km``, ``-o`` (also in ``-o/--output``).
_OPTION = re.compile(r"(?<![\w.-])(--[a-z][a-z0-9-]*|-[a-zA-Z])(?![\w-])")
#: Sections of shared options a command section takes in by naming them ("the recording
#: options").
_SHARED = {"recording options": "Options shared by commands that read a recording",
           "place options": "Options that place the recording"}


def _documented_options(section: str) -> set[str]:
    """Options named in code (inline backticks and fenced blocks) of one section."""
    code = re.findall(r"```.*?```", section, flags=re.S)
    code += re.findall(r"`([^`\n]+)`", re.sub(r"```.*?```", "", section, flags=re.S))
    return {m for piece in code for m in _OPTION.findall(piece)}


def _parser_options(command: str) -> set[str]:
    """Every option string of ``command`` as argparse has it (``--help`` left out)."""
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command").choices[command]
    return {s for a in sub._actions for s in a.option_strings if s not in ("-h", "--help")}


@pytest.mark.parametrize("command", _commands())
def test_cli_md_documents_every_option_and_no_other(command):
    """Each command's section of docs/cli.md names every option its parser has (the shared
    recording options by naming them), and names no option the command lacks."""
    sections = _sections()
    assert command in sections, f"docs/cli.md has no '## {command}' section"
    section = sections[command]
    documented = _documented_options(section)
    words = " ".join(section.split())
    for phrase, shared in _SHARED.items():
        if phrase in words:
            documented |= _documented_options(sections[shared])
    actual = _parser_options(command)
    assert not actual - documented, \
        f"docs/cli.md '## {command}' lacks {sorted(actual - documented)}"
    own = _documented_options(section)
    assert not own - actual, \
        f"docs/cli.md '## {command}' names options {command} does not have: {sorted(own - actual)}"


def test_batch_md_lists_the_summary_columns_in_order():
    from streamcal.batching import COLUMNS

    text = (DOCS / "batch.md").read_text(encoding="utf-8")
    documented = tuple(re.findall(r"^\| `(\w+)` \|", text, flags=re.M))
    assert documented == COLUMNS


@pytest.mark.slow
def test_batch_top_candidate_is_filled_whatever_the_verdict_as_batch_md_says(tmp_path):
    """A clean simulated track is at the noise floor, and its row still names the best-ranked
    candidate (docs/batch.md says so, rather than "empty unless an effect is missing")."""
    from streamcal.batching import diagnose_task
    from streamcal.diagnosis import diagnose
    from streamcal.sim import simulate

    track = simulate(duration_s=60, seed=4).track
    track.write(tmp_path / "clean.csv")
    row = diagnose_task(str(tmp_path / "clean.csv"))
    d = diagnose(track)
    assert row["verdict"] == d.verdict == "at_noise_floor"
    assert row["top_candidate"] == d.candidates[0].effect
    text = " ".join((DOCS / "batch.md").read_text(encoding="utf-8").split())
    assert "`top_candidate` | `diagnose` only: the best-ranked candidate effect, whatever the " \
           "verdict" in text


def test_the_fit_example_in_cli_md_is_what_fit_prints(capsys):
    """The example's lines, numbers aside, are the lines ``streamcal fit`` prints (units
    spelled as the program spells them: ``K [µT]``)."""
    section = _sections()["fit"]
    example = re.search(r"```\w*\n\$ streamcal fit (\S+) -o cal.json\n(.*?)```", section, re.S)
    track, shown = example.group(1), example.group(2)
    assert main(["fit", str(ROOT / track)]) == 0
    printed = capsys.readouterr().out.replace(str(ROOT / track), track)

    def shape(text):
        return [re.sub(r"-?\d+(\.\d+)?", "N", line) for line in text.splitlines()
                if not line.startswith("written:")]

    assert shape(printed) == shape(shown)
