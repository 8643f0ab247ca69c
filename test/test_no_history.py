"""Docs, code, configs and tests state what the product is and does, not how it got there.

History lives in git. A comment says why the code is as it is; a config says what it trains;
a doc gives the current numbers with the command that measures them. This test fails on the
marks of a development log in prose (Markdown, YAML and other text files whole; Python comments
and strings only, so code names such as ``v0`` of a pixel coordinate pass): numbered work
sessions, version labels of the weights (``v3``, ``v0-v3``, ``v8's``, ``weights v5``), "shipped
until", "was X, now Y" and "stage N of an earlier ...". Training stages are named by their
number and config file (``stage 3``, ``config/finetune_kp.yaml``), which describe the build.
"""
from __future__ import annotations

import io
from pathlib import Path
import re
import tokenize

from conftest import REPO
import pytest

ROOTS = ('README.md', 'Makefile', 'setup.py', 'setup.cfg', 'package.xml', '.ci', 'bags',
         'config', 'docs', 'launch', 'msg_adapters', 'scripts', 'semfeat_ros', 'test')
SUFFIXES = {'.py', '.md', '.yaml', '.yml', '.txt', '.xml', '.cfg', '.ini', '.toml', '.sh', ''}
SKIP_PARTS = {'__pycache__', 'out', 'build', 'install', 'log'}
THIS = Path(__file__).resolve()  # quotes the patterns it looks for

HISTORY = re.compile(r"""
    \bsessions?[ -][0-9]                                # a numbered work session
  | \b(?:earlier|previous|past|later|work(?:ing)?)\ sessions?\b
  | (?<![\w.<-])v[0-9]+\b(?![>.\w])                     # a version label: "v3", "v0-v3", "v8's"
  | \bshipped\ (?:until|since|before)\b
  | \bwas\b(?:[^.;\n]|\.(?=\S)){1,60},\ now\b          # "was X, now Y"
  | \bstage\ [0-9]+\ of\ (?:an|the)\ (?:earlier|previous|old)\b
""", re.IGNORECASE | re.VERBOSE)

PRINCIPAL_POINT = re.compile(r'\bu0\b')  # v0 beside u0: the image centre of a camera file


def text_files() -> list[Path]:
    files = []
    for root in ROOTS:
        path = REPO / root
        candidates = [path] if path.is_file() else sorted(path.rglob('*'))
        for p in candidates:
            rel = p.relative_to(REPO)
            if (p.is_file() and p.suffix in SUFFIXES and not SKIP_PARTS & set(rel.parts)
                    and p.resolve() != THIS):
                files.append(p)
    return files


def prose_lines(path: Path, text: str) -> list[tuple[int, str, str]]:
    """``(line number, prose, whole source line)``: every line of a text file; of a Python file
    its comments and string literals, line by line."""
    lines = text.splitlines()
    if path.suffix != '.py':
        return [(n, line, line) for n, line in enumerate(lines, 1)]
    out = []
    for tok in tokenize.generate_tokens(io.StringIO(text).readline):
        if tok.type in (tokenize.COMMENT, tokenize.STRING):
            for k, part in enumerate(tok.string.splitlines()):
                n = tok.start[0] + k
                out.append((n, part, lines[n - 1]))
    return out


def history_marks(prose: str, source_line: str) -> list[str]:
    """The history marks in one line of prose."""
    marks = []
    for m in HISTORY.finditer(prose):
        if m.group(0).lower() == 'v0' and PRINCIPAL_POINT.search(source_line):
            continue
        marks.append(m.group(0))
    return marks


def findings() -> list[tuple[str, int, str, str]]:
    found = []
    for path in text_files():
        try:
            text = path.read_text(encoding='utf-8')
        except UnicodeDecodeError:
            continue  # not a text file
        rel = path.relative_to(REPO).as_posix()
        for n, prose, line in prose_lines(path, text):
            for mark in history_marks(prose, line):
                found.append((rel, n, mark, line.strip()))
    return found


@pytest.mark.parametrize('line', [
    'Stage 3 of the shipped weights (v8, shipped until v9)',
    '# the first layer only, so v0-v3 weights keep their keys',
    'measured in {} 14 on the AVX-512 machine'.format('session'),  # not a finding here
    'on the machine of earlier sessions',
    'It is the session-15 probe',
    "descriptors stay bit-identical to v8's",
    'the threshold was 0.05, now 0.15',
    'weights v5 (stage 2)',
    'stage 2 of an earlier network',
])
def test_history_is_recognised(line: str) -> None:
    assert history_marks(line, line)


@pytest.mark.parametrize('line', [
    "_VISP_KEYS = ('px', 'py', 'u0', 'v0')",
    '| OS | Linux 6.18.44-fc-v1045 |',
    'semfeat-train --config config/finetune_kp.yaml --out out/train_v9',
    '<camera><px>615.5</px><u0>312.2</u0><v0>243.4</v0></camera>',
    'Stage 4 (config/finetune_kp.yaml) trains on from stage 3: static mIoU 0.643',
    'a session is built per input size (least recently used evicted)',
])
def test_present_tense_passes(line: str) -> None:
    assert not history_marks(line, line)


def test_prose_of_python_is_comments_and_strings() -> None:
    src = 'p0, v0 = cam.project(x)  # v3 weights\nname = "v5 shipped"\n'
    got = [(n, history_marks(p, line)) for n, p, line in prose_lines(Path('m.py'), src)]
    assert [(n, m) for n, m in got if m] == [(1, ['v3']), (2, ['v5'])]


def test_no_history_in_docs_code_configs_tests() -> None:
    left = [f'{rel}:{n}: {mark!r} in {line[:120]}' for rel, n, mark, line in findings()]
    assert not left, 'history told in the tree (say what is, not what was):\n' + '\n'.join(left)
