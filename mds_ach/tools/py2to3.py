"""``mds-ach py2to3``: the mechanical changes that let an original MDS-Ach Python 2 program run under Python 3.

The original programs (the paper's examples, ``mds_read.py``-style tools) are Python 2: ``print`` statements,
``raw_input``, ``except E, e:``, and golems' ``ach`` binding. Under Python 3 they stop at the first ``print`` with
a SyntaxError. This converter applies the few changes such programs need and nothing else, token by token (the
standard library's lib2to3 is gone from Python 3.13):

* ``print x, y`` -> ``print(x, y)``; ``print x,`` -> ``print(x, end=" ")``; ``print >>f, x`` ->
  ``print(x, file=f)``; a bare ``print`` -> ``print()``. ``print(x)`` is left as it is.
* ``import ach`` -> ``from mds_ach import ach`` (this package's binding, same API); ``import mds_ach as mds`` needs
  no change (this package provides the original module's names).
* ``raw_input`` -> ``input``, ``xrange`` -> ``range``, ``except E, e:`` -> ``except E as e:``, ``0777`` ->
  ``0o777``, ``<>`` -> ``!=``, ``d.has_key(k)`` -> ``(k in d)`` for a (dotted) name ``d``.

What it cannot decide from the text is reported, not changed: ``/`` between integers divides to a float in
Python 3 (a line with ``/`` is listed), backquotes, ``exec``/``unicode``/``long``/``basestring``. The result is
compiled; a program that still does not compile is an error (exit 1) naming the line.
"""

from __future__ import annotations

import argparse
import io
import re
import sys
import tokenize
from dataclasses import dataclass, field
from pathlib import Path

STATEMENT_START = {tokenize.NEWLINE, tokenize.INDENT, tokenize.DEDENT, tokenize.NL}
RENAMED = {"raw_input": "input", "xrange": "range"}
UNCHANGED_WARN = {"exec": "exec is a function in Python 3", "unicode": "no unicode type in Python 3 (str)",
                  "long": "no long type in Python 3 (int)", "basestring": "no basestring in Python 3 (str)"}
IMPORT_ACH = re.compile(r"^(?P<indent>[ \t]*)import[ \t]+ach(?P<alias>[ \t]+as[ \t]+\w+)?[ \t]*(?P<rest>#.*)?$")


@dataclass
class Result:
    """A converted program and what was done to it."""

    source: str
    changes: dict[str, int] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)  # "line N: ..." for what needs a look
    error: str = ""  # the converted program does not compile

    def count(self, what: str) -> None:
        self.changes[what] = self.changes.get(what, 0) + 1


class _Text:
    """The source as lines, for (row, col) spans from the tokenizer."""

    def __init__(self, source: str) -> None:
        self.lines = source.splitlines(keepends=True)
        self.starts = [0]
        for line in self.lines:
            self.starts.append(self.starts[-1] + len(line))
        self.source = source

    def at(self, pos: tuple[int, int]) -> int:
        return self.starts[pos[0] - 1] + pos[1]

    def span(self, a: tuple[int, int], b: tuple[int, int]) -> str:
        return self.source[self.at(a):self.at(b)]


def _significant(toks: list[tokenize.TokenInfo], i: int, step: int) -> int:
    """Index of the next (``step`` 1) or previous (-1) token that is not a comment or a non-logical newline."""
    i += step
    while 0 <= i < len(toks) and toks[i].type in (tokenize.COMMENT, tokenize.NL):
        i += step
    return i


def _statement_end(toks: list[tokenize.TokenInfo], i: int) -> int:
    """Index of the token that ends the simple statement starting after ``i``: NEWLINE, ENDMARKER or a ';' at
    bracket depth 0 (comments inside are part of the span's end only when they follow the last token)."""
    depth = 0
    j = i + 1
    while j < len(toks):
        t = toks[j]
        if t.type in (tokenize.NEWLINE, tokenize.ENDMARKER):
            return j
        if t.type == tokenize.OP:
            if t.string in "([{":
                depth += 1
            elif t.string in ")]}":
                depth -= 1
            elif t.string == ";" and depth == 0:
                return j
        j += 1
    return j


def _print_call(toks: list[tokenize.TokenInfo], i: int, end: int, text: _Text) -> str | None:
    """The Python 3 call for the print statement at token ``i`` (its tokens end before ``end``); None when it is
    already a call (``print(x)``)."""
    body = [k for k in range(i + 1, end) if toks[k].type not in (tokenize.COMMENT, tokenize.NL)]
    if not body:
        return "print()"
    first = toks[body[0]]
    if first.type == tokenize.OP and first.string == "(":
        depth, k = 0, body[0]
        for k in body:
            if toks[k].type == tokenize.OP and toks[k].string in "([{":
                depth += 1
            elif toks[k].type == tokenize.OP and toks[k].string in ")]}":
                depth -= 1
                if depth == 0:
                    break
        if k == body[-1]:
            return None  # print(...) as a whole: already a call (Python 2 printed a tuple for print (a, b))
    # split the items at top-level commas
    items: list[tuple[int, int]] = []
    depth, start = 0, body[0]
    for k in body:
        t = toks[k]
        if t.type == tokenize.OP and t.string in "([{":
            depth += 1
        elif t.type == tokenize.OP and t.string in ")]}":
            depth -= 1
        elif t.type == tokenize.OP and t.string == "," and depth == 0:
            items.append((start, k))
            start = _significant(toks, k, 1)
    trailing = toks[body[-1]].type == tokenize.OP and toks[body[-1]].string == ","
    if not trailing:
        items.append((start, body[-1] + 1))
    exprs = [text.span(toks[a].start, toks[b - 1].end) for a, b in items if a < b]
    target = None
    if exprs and exprs[0].startswith(">>"):
        target = exprs.pop(0)[2:].strip()
    args = exprs + ([f"file={target}"] if target else []) + (['end=" "'] if trailing else [])
    return f"print({', '.join(args)})"


def _pass(source: str, name: str, result: Result, prints: bool) -> str | None:
    """One pass of ``convert`` over ``source``: the print statements (``prints``) or every other change; None
    (``result.error`` set) when it cannot be tokenized."""
    text = _Text(source)
    try:
        toks = list(tokenize.generate_tokens(io.StringIO(source).readline))
    except (tokenize.TokenError, IndentationError, SyntaxError) as exc:
        result.source, result.error = source, f"{name}: cannot read it as Python: {exc}"
        return None
    edits: list[tuple[int, int, str]] = []  # (start offset, end offset, replacement)
    for i, t in enumerate(toks):
        prev = _significant(toks, i, -1)
        at_start = prev < 0 or toks[prev].type in STATEMENT_START or (
            toks[prev].type == tokenize.OP and toks[prev].string in (":", ";"))
        if prints:
            if t.type == tokenize.NAME and t.string == "print" and at_start:
                nxt = _significant(toks, i, 1)
                if nxt < len(toks) and toks[nxt].type == tokenize.OP and toks[nxt].string in ("=", ".", "["):
                    continue  # a name, not the statement
                end = _statement_end(toks, i)
                last = end - 1
                while last > i and toks[last].type in (tokenize.COMMENT, tokenize.NL):
                    last -= 1
                call = _print_call(toks, i, end, text)
                if call is not None:
                    edits.append((text.at(t.start), text.at(toks[last].end if last > i else t.end), call))
                    result.count("print statement -> print()")
            continue
        if t.type == tokenize.NAME and t.string in RENAMED and (prev < 0 or toks[prev].string != "."):
            edits.append((text.at(t.start), text.at(t.end), RENAMED[t.string]))
            result.count(f"{t.string} -> {RENAMED[t.string]}")
        elif t.type == tokenize.NAME and t.string == "except":
            end = _statement_end(toks, i)
            depth = 0
            for k in range(i + 1, end):
                s = toks[k]
                if s.type == tokenize.OP and s.string in "([{":
                    depth += 1
                elif s.type == tokenize.OP and s.string in ")]}":
                    depth -= 1
                elif s.type == tokenize.OP and s.string == ":" and depth == 0:
                    break
                elif s.type == tokenize.OP and s.string == "," and depth == 0:
                    edits.append((text.at(s.start), text.at(s.end), " as"))
                    result.count("except E, e -> except E as e")
                    break
        elif t.type == tokenize.NUMBER and t.string == "0" and i + 1 < len(toks) and \
                toks[i + 1].type == tokenize.NUMBER and toks[i + 1].start == t.end and toks[i + 1].string.isdigit():
            edits.append((text.at(t.start), text.at(toks[i + 1].end), "0o" + toks[i + 1].string))
            result.count("octal 0NNN -> 0oNNN")
        elif t.type == tokenize.OP and t.string == "<" and i + 1 < len(toks) and toks[i + 1].string == ">" and \
                toks[i + 1].start == t.end:
            edits.append((text.at(t.start), text.at(toks[i + 1].end), "!="))
            result.count("<> -> !=")
        elif t.type == tokenize.NAME and t.string == "has_key" and prev >= 1 and toks[prev].string == "." and \
                toks[prev - 1].type == tokenize.NAME and i + 1 < len(toks) and toks[i + 1].string == "(":
            close = _statement_end(toks, i)
            depth = 0
            for k in range(i + 1, close):
                if toks[k].string == "(":
                    depth += 1
                elif toks[k].string == ")":
                    depth -= 1
                    if depth == 0:
                        arg = text.span(toks[i + 2].start, toks[k - 1].end) if k > i + 2 else ""
                        first = prev - 1  # the object: a name or a dotted name (mds.__dict__)
                        while first >= 2 and toks[first - 1].string == "." and toks[first - 2].type == tokenize.NAME:
                            first -= 2
                        obj = text.span(toks[first].start, toks[prev - 1].end)
                        edits.append((text.at(toks[first].start), text.at(toks[k].end), f"({arg} in {obj})"))
                        result.count("d.has_key(k) -> (k in d)")
                        break
        elif t.type == tokenize.ERRORTOKEN and t.string == "`":
            result.notes.append(f"line {t.start[0]}: backquotes (repr): write repr(...)")
        elif t.type == tokenize.NAME and t.string in UNCHANGED_WARN and (prev < 0 or toks[prev].string != "."):
            result.notes.append(f"line {t.start[0]}: {t.string}: {UNCHANGED_WARN[t.string]}")
        elif t.type == tokenize.OP and t.string == "/":
            result.notes.append(f"line {t.start[0]}: '/' divides integers to a float in Python 3 (use // for the "
                                "Python 2 result)")
    out = source
    for start, end, new in sorted(edits, reverse=True):
        out = out[:start] + new + out[end:]
    return out


def convert(source: str, name: str = "<program>") -> Result:
    """``source`` with the mechanical Python 2 -> 3 changes applied (module docstring)."""
    result = Result(source)
    lines = source.splitlines(keepends=True)
    for n, line in enumerate(lines):
        m = IMPORT_ACH.match(line.rstrip("\r\n"))
        if m:
            eol = line[len(line.rstrip("\r\n")):]
            rest = f"  {m['rest']}" if m["rest"] else ""
            lines[n] = f"{m['indent']}from mds_ach import ach{m['alias'] or ''}{rest}{eol}"
            result.count("import ach -> from mds_ach import ach")
    source = "".join(lines)
    # two passes: every other change first, then the print statements, whose new text is built from the
    # (already changed) source of their arguments
    for prints in (False, True):
        converted = _pass(source, name, result, prints)
        if converted is None:
            return result
        source = converted
    result.source = source
    result.notes = list(dict.fromkeys(result.notes))
    try:
        compile(source, name, "exec")
    except SyntaxError as exc:
        result.error = f"{name}:{exc.lineno}: still not Python 3 after the conversion: {exc.msg}"
    return result


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.description = ("Convert an original MDS-Ach Python 2 program (print statements, 'import ach', raw_input, "
                     "'except E, e', ...) to Python 3 with this package's Ach binding. Prints the converted "
                     "program (one FILE), or with -w rewrites each FILE, keeping the original as FILE.py2. What "
                     "cannot be decided from the text (integer '/', backquotes, ...) is listed on stderr. Exit 1 "
                     "if a program still does not compile.")
    p.add_argument("files", nargs="+", metavar="FILE", help="Python 2 program(s)")
    p.add_argument("-w", "--write", action="store_true", help="rewrite the files (the original kept as FILE.py2)")


def run(args: argparse.Namespace) -> int:
    if len(args.files) > 1 and not args.write:
        print("mds-ach py2to3: several files need -w (rewrite them in place)", file=sys.stderr)
        return 2
    status = 0
    for name in args.files:
        path = Path(name)
        try:
            source = path.read_text()
        except (OSError, UnicodeDecodeError) as exc:
            print(f"mds-ach py2to3: {name}: cannot read it: {exc}", file=sys.stderr)
            status = 1
            continue
        result = convert(source, name)
        done = ", ".join(f"{what} ({n})" for what, n in result.changes.items()) or "nothing to change"
        print(f"{name}: {done}", file=sys.stderr)
        for note in result.notes:
            print(f"{name}: check {note}", file=sys.stderr)
        if result.error:
            print(f"mds-ach py2to3: {result.error}", file=sys.stderr)
            status = 1
            continue
        if args.write:
            if result.source != source:
                backup = path.with_name(path.name + ".py2")
                backup.write_text(source)
                path.write_text(result.source)
        else:
            sys.stdout.write(result.source)
    return status
