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
