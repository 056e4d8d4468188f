"""Every results command the README and the docs print resumes its committed folder (issue 28, item 3).

A results command is a ``bimp evaluate|sweep|frontier`` with ``--out results/...`` or a ``bimp merge`` with
``--into results/...``, in a code block (fenced or
indented) or in inline code. Blocks are read as the shell would, as far as the docs use it: ``\\`` continuation lines,
``#`` comments, ``;``, ``VAR=value`` and (nested) ``for VAR in a b c; do ... done`` loops. Each command runs in
process with ``--dry-run`` from the repository root and must find every episode done (a merge: every record
already copied). A command that cannot be read
(an unbalanced quote, an elided ``...`` in a block that writes ``results/``, an unknown variable) fails naming its
file and line: the docs must stay runnable. A command that only older code can run is printed as history,
``(git switch --detach COMMIT && bimp ...)``: not a command of the current code, so not run here; such a subshell
may hold a loop or go on over several lines, and everything up to its closing ``)`` is history.
``make check-results`` runs this file alone.
"""

from __future__ import annotations

import re
import shlex
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from bimp.agents.cli import main

ROOT = Path(__file__).resolve().parent.parent
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]  # docs/studies/ too: their commands resume
HEADLINE = {"results/paper", "results/rl"}
RESULTS_COMMAND = re.compile(r"\bbimp\s+(evaluate|sweep|frontier|merge)\b")
VARIABLE = re.compile(r"\$(?:\{(\w+)\}|(\w+))")
ASSIGNMENT = re.compile(r"[A-Za-z_]\w*=\S*")


@dataclass
class Command:
    where: str  # "file:line", and the loop variables' values
    argv: list[str] = field(default_factory=list)  # after "bimp"
    problem: str = ""  # why it cannot be run as printed

    @property
    def out(self) -> str:
        flag = "--into" if self.argv[:1] == ["merge"] else "--out"
        for i, token in enumerate(self.argv):
            if token == flag and i + 1 < len(self.argv):
                return self.argv[i + 1]
            if token.startswith(f"{flag}="):
                return token.removeprefix(f"{flag}=")
        return ""


# --- reading the markdown ----------------------------------------------------------------------------------------
def code_blocks(lines: list[str]) -> tuple[list[tuple[int, list[str]]], set[int]]:
    """``(first line number, lines)`` of each fenced or indented (4 spaces after a blank line) code block, and the
    numbers of the lines they take (fences included)."""
    blocks, inside, i = [], set(), 0
    while i < len(lines):
        if lines[i].lstrip().startswith("```"):
            end = next((j for j in range(i + 1, len(lines)) if lines[j].lstrip().startswith("```")), len(lines))
            blocks.append((i + 2, lines[i + 1:end]))
            inside.update(range(i + 1, end + 2))
            i = end + 1
        elif lines[i].startswith("    ") and (i == 0 or not lines[i - 1].strip()):
            end = i
            while end < len(lines) and (lines[end].startswith("    ") or not lines[end].strip()):
                end += 1
            blocks.append((i + 1, [line[4:] for line in lines[i:end]]))
            inside.update(range(i + 1, end + 1))
            i = end
        else:
            i += 1
    return blocks, inside


def inline_code(lines: list[str], inside: set[int]) -> list[tuple[int, str]]:
    """``(line number, code)`` of each inline code span outside the blocks (a span may go on over a line break)."""
    text = "\n".join("" if n in inside else line for n, line in enumerate(lines, 1))
    return [(text.count("\n", 0, m.start()) + 1, " ".join(m.group(1).split()))
            for m in re.finditer(r"(?<!`)`([^`]+)`(?!`)", text)]


# --- reading a block as the shell would ---------------------------------------------------------------------------
def split_unquoted(text: str, separator: str) -> list[str]:
    """``text`` split at ``separator`` outside quotes; at ``#`` (a comment) the rest is dropped."""
    parts, current, quote = [], "", ""
    for k, char in enumerate(text):
        if quote:
            quote = "" if char == quote else quote
        elif char in "'\"":
            quote = char
        elif char == "#" and (k == 0 or text[k - 1].isspace()):
            break
        elif char == separator:
            parts.append(current)
            current = ""
            continue
        current += char
    return [*parts, current]


def statements(start: int, body: list[str]) -> list[tuple[int, str]]:
    """``(line number, statement)``: continuation lines joined, comments dropped, split at ``;``."""
    result, pending, first = [], "", None
    for n, line in enumerate(body, start):
        first = n if first is None else first
        if line.rstrip().endswith("\\"):
            pending += line.rstrip()[:-1] + " "
            continue
        for part in split_unquoted(pending + line, ";"):
            if part.strip():
                result.append((first, part.strip()))
        pending, first = "", None
    if pending.strip():
        result.append((first, pending.strip()))
    return result


def expand(path: str, stmts: list[tuple[int, str]], env: dict[str, str] | None = None) -> list[Command]:
    """The commands ``bimp evaluate|sweep|frontier|merge`` that ``stmts`` run, loops unrolled, variables substituted."""
    env, commands, i = dict(env or {}), [], 0
    while i < len(stmts):
        line, text = stmts[i]
        where = f"{path}:{line}" + "".join(f" {k}={v}" for k, v in env.items())
        word = text.split()[0]
        if text.startswith("("):  # a subshell, `(git switch --detach COMMIT && ...)`: history, skipped to its `)`
            depth = 0
            while i < len(stmts):
                depth += stmts[i][1].count("(") - stmts[i][1].count(")")
                i += 1
                if depth <= 0:
                    break
            continue
        if word == "for":
            head = text.split()
            if len(head) < 4 or head[2] != "in" or i + 1 >= len(stmts) or stmts[i + 1][1].split()[0] != "do":
                return [*commands, Command(where, problem=f"cannot read the loop {text!r}")]
            rest = stmts[i + 1][1][2:].strip()  # what follows `do` on its line: the body's first statement
            body = [(stmts[i + 1][0], rest)] if rest else []
            depth, j = 1 + (rest.split()[:1] == ["for"]), i + 2
            while j < len(stmts) and depth:
                first = stmts[j][1].split()[0]
                depth += (first == "for") - (first == "done")
                if depth:
                    body.append(stmts[j])
                j += 1
            if depth:
                return [*commands, Command(where, problem=f"the loop {text!r} has no `done`")]
            for value in head[3:]:
                commands += expand(path, body, {**env, head[1]: value})
            i = j
            continue
        if ASSIGNMENT.fullmatch(text):
            name, _, value = text.partition("=")
            env[name] = value
        elif RESULTS_COMMAND.match(text):
            unknown = sorted({a or b for a, b in VARIABLE.findall(text)} - set(env))
            if unknown:
                commands.append(Command(where, problem=f"unknown variable(s) {unknown} in {text!r}"))
            else:
                commands.append(command(where, VARIABLE.sub(lambda m: env[m.group(1) or m.group(2)], text)))
        i += 1
    return commands


def command(where: str, text: str) -> Command:
    try:
        tokens = shlex.split(text)
    except ValueError as err:
        return Command(where, problem=f"cannot be parsed ({err}): {text!r}")
    if "..." in tokens:
        return Command(where, tokens[1:], problem=f"elided (`...`): spell it out so it can be run: {text!r}")
    return Command(where, tokens[1:])


def documented_commands() -> list[Command]:
    """Every results command of README.md and docs/*.md, and the unrunnable ones of a block that writes results/."""
    found = []
    for doc in DOCS:
        path, lines = str(doc.relative_to(ROOT)), doc.read_text().splitlines()
        blocks, inside = code_blocks(lines)
        for start, body in blocks:
            commands = expand(path, statements(start, body))
            writes_results = any(c.out.startswith("results/") for c in commands)
            found += [c for c in commands if c.out.startswith("results/") or (c.problem and writes_results)]
        for line, code in inline_code(lines, inside):
            if RESULTS_COMMAND.match(code):
                found += [c for c in [command(f"{path}:{line}", code)] if c.out.startswith("results/")]
    return found


COMMANDS = documented_commands()


def test_the_extraction_finds_the_headline_folders():
    folders = {c.out.rstrip("/") for c in COMMANDS}
    assert HEADLINE <= folders, f"missing: {sorted(HEADLINE - folders)}; found {sorted(folders)}"


def test_the_reader_unrolls_loops_and_joins_lines():
    block = ["N=3", "for A in ppo sac; do for S in 1 2; do bimp evaluate --policy $A \\",
             "    --label $A-s$S --episodes $N --out results/x; done; done   # a comment"]
    commands = expand("doc.md", statements(10, block))
    assert [c.argv for c in commands] == [["evaluate", "--policy", a, "--label", f"{a}-s{s}", "--episodes", "3",
                                           "--out", "results/x"] for a in ("ppo", "sac") for s in ("1", "2")]
    assert [c.where for c in commands][:2] == ["doc.md:11 N=3 A=ppo S=1", "doc.md:11 N=3 A=ppo S=2"]
    history = ["(git switch --detach abc1234 && for P in enkts enks; do", "  bimp evaluate --policy $P \\",
               "      --out results/old", "done)   # history", "bimp evaluate --policy enkts --out results/new"]
    assert [c.argv for c in expand("doc.md", statements(1, history))] == [
        ["evaluate", "--policy", "enkts", "--out", "results/new"]]
    assert "elided" in command("doc.md:1", "bimp evaluate ... --out results/x").problem
    assert "cannot be parsed" in command("doc.md:1", "bimp evaluate --set 'a=1 --out results/x").problem


def _files(folder: Path) -> dict[str, tuple[int, int]]:
    return {str(p): (p.stat().st_size, p.stat().st_mtime_ns) for p in folder.rglob("*")} if folder.exists() else {}


@pytest.mark.parametrize("cmd", COMMANDS, ids=[c.where for c in COMMANDS])
def test_the_documented_command_finds_its_episodes_done(cmd, monkeypatch, capsys):
    if cmd.problem:
        pytest.fail(f"{cmd.where}: {cmd.problem}")
    monkeypatch.chdir(ROOT)
    before = _files(ROOT / cmd.out)
    shown = f"{cmd.where}: `bimp {shlex.join(cmd.argv)} --dry-run`"
    try:
        status = main([*cmd.argv, "--dry-run"])
    except SystemExit as exit:  # argparse refusing the arguments
        status = exit.code
    out, err = capsys.readouterr()
    assert _files(ROOT / cmd.out) == before, f"{shown} wrote into {cmd.out}"
    assert status == 0, f"{shown} exited {status}: {err.strip()[-3000:]}"
    last = out.strip().splitlines()[-1] if out.strip() else ""
    done = r"\S+: would copy 0 record\(s\), \d+ already there" if cmd.argv[0] == "merge" else \
        r"dry run: 0 episode\(s\) would run"
    assert re.fullmatch(done, last), f"{shown} would run episodes or copy records:\n{out[-3000:]}"
