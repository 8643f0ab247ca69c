"""``semfeat-report``: rewrite the results tables of a document from the evaluation outputs.

    semfeat-report                        # rewrite docs/RESULTS.md from config/report.yaml
    semfeat-report --check                # exit 1 when the document's tables differ
    semfeat-report --set real=out/eval_real   # read source ``real`` from another directory

The manifest (YAML, ``config/report.yaml``) names the result directories once (``sources``:
a directory and the command that writes it) and, for each table, which JSON file of the
directory, which methods (rows or columns) and which values. The document holds each table
between ``<!-- semfeat-report:NAME -->`` and ``<!-- /semfeat-report -->``; the text between
the markers is replaced (the table, then the inputs with their commands), everything outside
is left as it is. Only the document is written (a temporary file renamed into place, never
through a symbolic link). Bad input gives one line on stderr and exit status 1 (2 for a bad
command line); ``--check`` exits 1 when a table differs from what its inputs give.
"""
from __future__ import annotations

import argparse
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
import json
import math
from pathlib import Path
import re
import sys
from typing import Any

import yaml

from semfeat_ros.conf import merge_conf
from semfeat_ros.paths import write_text_atomic
from semfeat_ros.tools.cli import OneLineParser, error_line
from semfeat_ros.tools.errors import (
    ReportError,
    ReportInputError,
    ReportManifestError,
    ReportOutputError,
)

PROG = 'semfeat-report'
DEFAULT_MANIFEST = Path('config/report.yaml')
END_MARKER = '<!-- /semfeat-report -->'
_BLOCK = re.compile(r'<!-- semfeat-report:([A-Za-z0-9_-]+) -->\n(.*?)' + re.escape(END_MARKER),
                    re.DOTALL)
_MMA = re.compile(r'mma@(\d+(?:\.\d+)?)')


def begin_marker(name: str) -> str:
    """The comment that opens the block of table ``name``."""
    return f'<!-- semfeat-report:{name} -->'


@dataclass(frozen=True)
class Source:
    """One result directory and the command that writes it (``{dir}`` stands for it)."""

    name: str
    dir: str
    command: str


def _mapping(value: Any, what: str) -> Mapping[str, Any]:
    if not isinstance(value, Mapping):
        raise ReportManifestError(f'{what}: expected a mapping, got {type(value).__name__}')
    return value


def _text(value: Any, what: str) -> str:
    if not isinstance(value, str) or not value:
        raise ReportManifestError(f'{what}: expected a non-empty string, got {value!r}')
    return value


def load_manifest(path: Path) -> dict[str, Any]:
    """The manifest at ``path`` (``yaml.safe_load``), its top-level layout checked.

    Raises:
        ReportInputError: the file does not exist.
        ReportManifestError: not YAML, or no ``sources`` / ``tables`` mappings.
    """
    if not path.is_file():
        raise ReportInputError(f'manifest not found: {path}')
    try:
        data = yaml.safe_load(path.read_text(encoding='utf-8'))
    except yaml.YAMLError as exc:
        raise ReportManifestError(f'{path}: not valid YAML ({error_line(exc)})') from exc
    data = dict(_mapping(data, str(path)))
    unknown = sorted(set(data) - {'doc', 'sources', 'tables'})
    if unknown:
        raise ReportManifestError(f'{path}: unknown keys {", ".join(unknown)}; known keys: '
                                  'doc, sources, tables')
    _mapping(data.get('sources'), f'{path}: sources')
    _mapping(data.get('tables'), f'{path}: tables')
    return data


def parse_sources(manifest: Mapping[str, Any], overrides: Mapping[str, str]) -> dict[str, Source]:
    """The manifest's sources with ``overrides`` (name -> directory) applied.

    Raises:
        ReportManifestError: a source without ``dir`` / ``command``, or an override naming no
            source.
    """
    sources: dict[str, Source] = {}
    for name, spec in manifest['sources'].items():
        spec = _mapping(spec, f'sources.{name}')
        sources[name] = Source(name, _text(spec.get('dir'), f'sources.{name}.dir'),
                               _text(spec.get('command'), f'sources.{name}.command'))
    for name, directory in overrides.items():
        if name not in sources:
            raise ReportManifestError(f'--set {name}=...: no source {name!r}; sources: '
                                      f'{", ".join(sorted(sources))}')
        sources[name] = Source(name, directory, sources[name].command)
    return sources


def _lookup(data: Any, path: str, where: str) -> Any:
    """The value at dotted ``path``; ``mma@N`` is the ``mma`` entry at threshold N px."""
    node = data
    parts = path.split('.')
    for i, part in enumerate(parts):
        mma = _MMA.fullmatch(part)
        if mma is not None and isinstance(node, Mapping) and i == len(parts) - 1:
            curve, px = node.get('mma'), node.get('mma_thresholds_px')
            if isinstance(curve, list) and isinstance(px, list) and float(mma[1]) in px:
                return curve[px.index(float(mma[1]))]
            raise ReportInputError(f'{where}: no MMA at {mma[1]} px under {path}')
        if not isinstance(node, Mapping) or part not in node:
            raise ReportInputError(f'{where}: no value at {path}')
        node = node[part]
    return node


def format_value(value: Any, fmt: str, scale: float, where: str) -> str:
    """``value`` times ``scale`` in format ``fmt``; lists and mappings of numbers become
    ``a/b/c`` (mappings in key order)."""
    if isinstance(value, Mapping):
        value = list(value.values())
    if isinstance(value, list):
        return '/'.join(format_value(v, fmt, scale, where) for v in value)
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ReportInputError(f'{where}: expected a number, got {value!r}')
    if not math.isfinite(value):
        return 'n/a'
    try:
        return format(value * scale, fmt)
    except ValueError as exc:
        raise ReportManifestError(f'{where}: bad format {fmt!r}') from exc


class _Reader:
    """Reads and caches the JSON files of the sources, relative to ``root``."""

    def __init__(self, root: Path, sources: Mapping[str, Source]) -> None:
        self.root = root
        self.sources = sources
        self.cache: dict[Path, Any] = {}

    def path(self, source: str, file: str, where: str) -> Path:
        if source not in self.sources:
            raise ReportManifestError(f'{where}: no source {source!r}')
        return Path(self.sources[source].dir) / file

    def load(self, source: str, file: str, where: str) -> Any:
        rel = self.path(source, file, where)
        src = self.sources[source]
        directory = self.root / src.dir
        if not directory.is_dir():
            raise ReportInputError(f'{where}: input directory {src.dir} (source {source}) not '
                                   f'found; it is written by: '
                                   f'{src.command.format(dir=src.dir)}')
        full = self.root / rel
        if full not in self.cache:
            if not full.is_file():
                raise ReportInputError(f'{where}: {rel} not found (source {source})')
            try:
                self.cache[full] = json.loads(full.read_text(encoding='utf-8'))
            except json.JSONDecodeError as exc:
                raise ReportInputError(f'{where}: {rel} is not valid JSON ({exc.msg}, line '
                                       f'{exc.lineno})') from exc
        return self.cache[full]


_TABLE = {'file': 'results.json', 'prefix': '', 'label_header': None, 'columns': None,
          'rows': None}
_COLUMN = {'header': None, 'method': None, 'metric': None, 'format': None, 'scale': None}
_ROW = {'label': None, 'source': None, 'method': None, 'metric': None, 'format': None,
        'scale': None, 'sources': {}, 'mean_of': None}


def _pick(*values: Any, default: Any = None) -> Any:
    """The first value that is not None."""
    return next((v for v in values if v is not None), default)


def _mean_sources(row: Mapping[str, Any], where: str) -> list[str]:
    """The sources a ``mean_of`` row averages ([] for an ordinary row)."""
    if row['mean_of'] is None:
        return []
    if row['source'] is not None or row['sources']:
        raise ReportManifestError(f'{where}: mean_of replaces source and sources')
    if not isinstance(row['mean_of'], list) or not row['mean_of']:
        raise ReportManifestError(f'{where}.mean_of: needs a non-empty list of sources')
    return [_text(s, f'{where}.mean_of[{i}]') for i, s in enumerate(row['mean_of'])]


def _mean(values: list[Any], where: str) -> float:
    """Mean of the numbers ``values`` (a ``mean_of`` cell)."""
    bad = [v for v in values if isinstance(v, bool) or not isinstance(v, int | float)]
    if bad:
        raise ReportInputError(f'{where}: mean_of needs numbers, got {bad[0]!r}')
    return float(sum(values)) / len(values)


def render_table(name: str, spec: Mapping[str, Any], reader: _Reader) -> str:
    """The markdown of table ``name``: the table, then its inputs with their commands.

    A cell's value is the row's source's file at ``prefix.metric`` (``{method}`` in the prefix
    is the column's, else the row's method; ``metric``, ``format`` and ``scale`` likewise); a
    row's ``sources`` maps a column header to another source for that cell. A row with
    ``mean_of`` (a list of sources, instead of ``source``) holds the mean of each cell's value
    over those sources (numbers only).
    """
    where = f'tables.{name}'
    t = merge_conf(_TABLE, spec, ReportManifestError, name=where, opaque=('columns', 'rows'))
    file = _text(t['file'], f'{where}.file')
    if not isinstance(t['columns'], list) or not t['columns'] or \
            not isinstance(t['rows'], list) or not t['rows']:
        raise ReportManifestError(f'{where}: needs non-empty lists columns and rows')
    columns = [merge_conf(_COLUMN, c, ReportManifestError, name=f'{where}.columns[{i}]')
               for i, c in enumerate(t['columns'])]
    headers = [_text(c['header'], f'{where}.columns[{i}].header')
               for i, c in enumerate(columns)]
    lines = ['| ' + ' | '.join([_text(t['label_header'], f'{where}.label_header')] + headers)
             + ' |', '|---|' + '---:|' * len(columns)]
    used: list[str] = []
    for r, spec_row in enumerate(t['rows']):
        row = merge_conf(_ROW, spec_row, ReportManifestError, name=f'{where}.rows[{r}]',
                         opaque=('sources', 'mean_of'))
        label = _text(row['label'], f'{where}.rows[{r}].label')
        overrides = _mapping(row['sources'], f'{where}.rows[{r}].sources')
        stray = sorted(set(overrides) - set(headers))
        if stray:
            raise ReportManifestError(f'{where}.rows[{r}].sources: no column {", ".join(stray)}')
        mean_of = _mean_sources(row, f'{where}.rows[{r}]')
        cells = [label]
        for col, header in zip(columns, headers, strict=True):
            cell = f'table {name}, row {label!r}, column {header!r}'
            metric = _text(_pick(col['metric'], row['metric']), f'{cell}: metric')
            method = _pick(col['method'], row['method'], default='')
            path = '.'.join(p for p in (str(t['prefix']).format(method=method), metric) if p)
            cell_sources = mean_of or [_text(overrides.get(header, row['source']),
                                             f'{cell}: source')]
            values = [_lookup(reader.load(source, file, cell), path, f'{cell} ({source})')
                      for source in cell_sources]
            value = values[0] if not mean_of else _mean(values, cell)
            cells.append(format_value(value, str(_pick(col['format'], row['format'],
                                                       default='.1f')),
                                      float(_pick(col['scale'], row['scale'], default=1.0)),
                                      cell))
            used += [source for source in cell_sources if source not in used]
        lines.append('| ' + ' | '.join(cells) + ' |')
    lines += ['', 'Inputs (`semfeat-report` rewrites this table from them):', '']
    for source in used:
        src = reader.sources[source]
        lines.append(f'- `{reader.path(source, file, name).as_posix()}`: '
                     f'`{src.command.format(dir=src.dir)}`')
    return '\n'.join(lines) + '\n'


def render_document(text: str, tables: Mapping[str, str]) -> str:
    """``text`` with the content of each marker block replaced by ``tables[name]``.

    Raises:
        ReportManifestError: a block the manifest has no table for, a table without a block,
            a block opened twice or never closed.
    """
    found = _BLOCK.findall(text)
    names = [n for n, _ in found]
    opened = re.findall(r'<!-- semfeat-report:([A-Za-z0-9_-]+) -->', text)
    if len(opened) != len(names) or text.count(END_MARKER) != len(names):
        raise ReportManifestError('unbalanced semfeat-report markers in the document')
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ReportManifestError(f'tables in the document more than once: {", ".join(dup)}')
    extra = sorted(set(names) - set(tables))
    missing = sorted(set(tables) - set(names))
    if extra or missing:
        raise ReportManifestError(
            f'document and manifest disagree: blocks without a table: {", ".join(extra) or "-"}'
            f'; tables without a block: {", ".join(missing) or "-"}')
    return _BLOCK.sub(lambda m: f'{begin_marker(m[1])}\n{tables[m[1]]}{END_MARKER}', text)


def write_atomic(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` atomically (:func:`~semfeat_ros.paths.write_text_atomic`);
    refuses a symbolic link (the document is the only file written)."""
    if path.is_symlink():
        raise ReportOutputError(f'{path} is a symbolic link; refusing to write through it')
    write_text_atomic(path, text)


@dataclass(frozen=True)
class Outcome:
    """What :func:`main` did: the document, its tables and the ones that differed."""

    doc: Path
    tables: tuple[str, ...]
    changed: tuple[str, ...]


def main(manifest_path: Path, *, doc: Path | None = None, root: Path = Path('.'),
         overrides: Mapping[str, str] | None = None, check: bool = False) -> Outcome:
    """Regenerate the tables of ``doc`` (default: the manifest's ``doc``) from the manifest.

    Paths in the manifest are relative to ``root``. With ``check`` nothing is written.

    Raises:
        ReportError: a bad manifest or document, a missing input.
    """
    manifest = load_manifest(manifest_path)
    sources = parse_sources(manifest, overrides or {})
    if doc is None:
        doc = root / _text(manifest.get('doc'), f'{manifest_path}: doc')
    if not doc.is_file():
        raise ReportInputError(f'document not found: {doc}')
    reader = _Reader(root, sources)
    tables = {name: render_table(name, spec, reader)
              for name, spec in manifest['tables'].items()}
    text = doc.read_text(encoding='utf-8')
    current = dict(_BLOCK.findall(text))
    new = render_document(text, tables)
    changed = tuple(n for n in tables if current.get(n) != tables[n])
    if not check and new != text:
        write_atomic(doc, new)
    return Outcome(doc, tuple(tables), changed)


def _parse_set(items: Sequence[str]) -> dict[str, str]:
    out: dict[str, str] = {}
    for item in items:
        name, sep, directory = item.partition('=')
        if not sep or not name or not directory:
            raise ReportManifestError(f'--set {item!r}: expected NAME=DIR')
        out[name] = directory
    return out


def build_parser() -> argparse.ArgumentParser:
    p = OneLineParser.for_tool(PROG, __doc__)
    p.add_argument('--manifest', type=Path, default=DEFAULT_MANIFEST,
                   help=f'report manifest (default: {DEFAULT_MANIFEST})')
    p.add_argument('--doc', type=Path, default=None,
                   help="document to rewrite (default: the manifest's doc, under --root)")
    p.add_argument('--root', type=Path, default=Path('.'),
                   help="directory the manifest's paths are relative to (default: the cwd)")
    p.add_argument('--set', action='append', default=[], metavar='NAME=DIR',
                   help='read source NAME from DIR (repeatable)')
    p.add_argument('--check', action='store_true',
                   help='write nothing; exit 1 when a table differs from its inputs')
    return p


def cli(argv: list[str] | None = None) -> int:
    """Console-script entry point; returns the exit status."""
    args = build_parser().parse_args(argv)
    try:
        out = main(args.manifest, doc=args.doc, root=args.root,
                   overrides=_parse_set(args.set), check=args.check)
    except (ReportError, OSError) as exc:
        print(f'{PROG}: error: {error_line(exc)}', file=sys.stderr)
        return 1
    if args.check:
        if out.changed:
            print(f'{PROG}: {out.doc}: tables differ from their inputs: '
                  f'{", ".join(out.changed)} (run {PROG} to rewrite them)', file=sys.stderr)
            return 1
        print(f'{PROG}: {out.doc}: {len(out.tables)} tables match their inputs')
        return 0
    print(f'{PROG}: {out.doc}: {len(out.tables)} tables, rewrote '
          f'{", ".join(out.changed) if out.changed else "none"}')
    return 0


if __name__ == '__main__':
    sys.exit(cli())
