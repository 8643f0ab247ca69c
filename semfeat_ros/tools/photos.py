"""``semfeat-photos``: collect real photographs from Debian packages and installed wheels.

usage: semfeat-photos --out OUT [--config config/photos.yaml] [--deb-dir DIR] [--only NAME]...
                      [--max-side 1280] [--quality 92] [--min-textured 0.25] [--min-side 160]
                      [--quiet]

Every source of the list (default: the shipped ``config/photos.yaml``) is a Debian package or
``module:NAME``, a package inside an installed wheel. A Debian package is fetched with
``apt-get download`` into ``OUT/cache/debs`` (or taken from ``--deb-dir``, a folder of .deb files
already downloaded; then no registry is asked), unpacked with ``dpkg-deb -x`` into
``OUT/cache/unpacked/<package>`` (nothing is installed; the unpacked tree is removed afterwards)
and its licence read from ``usr/share/doc/<package>/copyright``. The images matching the
source's globs (regular files only: symlinks are skipped) are written as
``OUT/images/<package>__<stem>.jpg``: 8-bit RGB, long side at most ``--max-side`` px (area
downscaling), JPEG quality ``--quality``; a stem that several files of a source share is
prefixed with the path components that tell them apart. ``OUT/manifest.json`` lists one record
per image: package, version, path inside the package, licence and copyright line, original and
output size (px), sha256 of the output file, textured fraction.

Two measured filters drop what curation missed: images whose short side is under ``--min-side``
px, and nearly flat images, whose fraction of textured 16x16 px blocks (grey-level standard
deviation >= 4 at 640 px on the long side) is under ``--min-textured``. Byte-identical source
files are kept once.

The run is idempotent: a source whose record in ``OUT/cache/done`` matches the current options
and whose outputs are intact is skipped (no download). A failing source (no apt lists, download
refused, broken .deb, missing copyright file, a licence the list does not declare) is reported in
one line and the others go on; the exit status is non-zero only if nothing was collected, or for
a bad ``--out`` / ``--config`` / ``--deb-dir``. Every output path stays inside ``--out``: a symlink
leading out of it is refused.

Licences: the photographs are used for training only and are never committed (``out/`` is not
in git); what the repository holds is the list of sources with their licences
(``config/photos.yaml``), and the manifest records each image's licence as its package states it.
"""
from __future__ import annotations

import argparse
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
import glob as globmod
import hashlib
import importlib.metadata
import importlib.util
import json
import os
from pathlib import Path
import re
import shutil
import subprocess
import sys
import time
from typing import Any

import cv2
import numpy as np
from tqdm import tqdm
import yaml

from semfeat_ros.tools.cli import OneLineParser, error_line

PROG = 'semfeat-photos'
FORMAT_VERSION = 1  # of OUT/cache/done/*.json; a change redoes every source
EXCLUDED_PACKAGES = ('visp-images-data',)  # the project's real-sequence evaluation set
EVALUATION_ONLY = 'real_fisheye_calib'     # ../shared/data/real_fisheye_calib
_DEB_NAME = re.compile(r'^[a-z0-9][a-z0-9+.-]+$')
_MODULE_NAME = re.compile(r'^[A-Za-z_][A-Za-z0-9_]*$')
TEXTURE_BLOCK_PX = 16
TEXTURE_MIN_STD = 4.0      # grey levels (0-255)
TEXTURE_LONG_SIDE_PX = 640
_COMMAND_TIMEOUT_S = 900


class PhotoToolError(Exception):
    """Base class of the errors of ``semfeat-photos``; every message is one line."""


class PhotoConfigError(PhotoToolError, ValueError):
    """The list of sources (``photos.yaml``) or an option is invalid."""


class OutputConfinementError(PhotoToolError, OSError):
    """An output path would leave ``--out`` (through a symlink) or is not a directory."""


class SourceError(PhotoToolError):
    """One source cannot be collected; the others go on."""


class PackageDownloadError(SourceError):
    """``apt-get download`` failed (no apt lists, unknown package, download refused), or the
    package's .deb is missing from ``--deb-dir``."""


class DebFormatError(SourceError):
    """A .deb file cannot be read by ``dpkg-deb`` or holds another package."""


class CopyrightError(SourceError):
    """The package's copyright file is missing or does not support the declared licence."""


class NoImagesError(SourceError):
    """No usable image matched the source's globs."""


# ------------------------------------------------------------------------------ the list


@dataclass(frozen=True)
class PhotoSource:
    """One entry of ``photos.yaml``.

    Attributes:
        package: Debian package name, or ``module:NAME`` for a package inside an installed wheel.
        globs: glob patterns of image files, relative to the unpacked package root (Debian) or
            to the module's directory (wheels).
        licence: the licence the copyright file or notice states for these files.
        copyright_root: installed directory (relative) that the copyright file's ``Files:``
            patterns are relative to; default: the package root.
        source_dir: prefix of those patterns for ``copyright_root`` (e.g. ``samples``).
        evidence: phrase that must occur in the copyright file / notice (required for Debian
            copyright files that are not machine-readable).
        notice: wheels: file (relative to the module) stating the licence; default: the wheel's
            metadata.
    """

    package: str
    globs: tuple[str, ...]
    licence: str
    copyright_root: str = ''
    source_dir: str = ''
    evidence: str = ''
    notice: str = ''

    @property
    def is_wheel(self) -> bool:
        return self.package.startswith('module:')

    @property
    def name(self) -> str:
        """Prefix of the output files: the Debian package or the module name."""
        return self.package[len('module:'):] if self.is_wheel else self.package


def _relative_pattern(value: str, what: str) -> str:
    p = str(value).strip()
    if not p or p.startswith('/') or '..' in Path(p).parts:
        raise PhotoConfigError(f'{what}: {value!r} must be a relative path without ".."')
    return p


def load_sources(path: Path) -> list[PhotoSource]:
    """Read and check ``photos.yaml`` (yaml.safe_load): a mapping with a ``sources`` list."""
    try:
        data = yaml.safe_load(Path(path).read_text(encoding='utf-8'))
    except OSError as exc:
        raise PhotoConfigError(f'cannot read {path}: {exc.strerror or exc}') from exc
    except yaml.YAMLError as exc:
        raise PhotoConfigError(f'{path}: invalid YAML: {error_line(exc)}') from exc
    if not isinstance(data, dict) or not isinstance(data.get('sources'), list):
        raise PhotoConfigError(f'{path}: expected a mapping with a "sources" list')
    sources: list[PhotoSource] = []
    allowed = {f for f in PhotoSource.__dataclass_fields__}
    for k, entry in enumerate(data['sources']):
        where = f'{path}: sources[{k}]'
        if not isinstance(entry, dict):
            raise PhotoConfigError(f'{where}: expected a mapping')
        unknown = set(entry) - allowed
        if unknown:
            raise PhotoConfigError(f'{where}: unknown keys {sorted(unknown)}')
        package = str(entry.get('package', '')).strip()
        name = package[len('module:'):] if package.startswith('module:') else package
        ok = (_MODULE_NAME if package.startswith('module:') else _DEB_NAME).match(name)
        if not ok:
            raise PhotoConfigError(f'{where}: invalid package {package!r} (a Debian package '
                                   f'name or module:NAME)')
        if package in EXCLUDED_PACKAGES:
            raise PhotoConfigError(f'{where}: {package} is the evaluation sequence set and '
                                   'must never be used for training')
        globs = entry.get('globs')
        if isinstance(globs, str):
            globs = [globs]
        if not isinstance(globs, list) or not globs:
            raise PhotoConfigError(f'{where}: "globs" must be a non-empty list')
        globs = tuple(_relative_pattern(g, f'{where}.globs') for g in globs)
        licence = str(entry.get('licence') or '').strip()
        if not licence:
            raise PhotoConfigError(f'{where}: "licence" is required')
        src = PhotoSource(
            package=package, globs=globs, licence=licence,
            copyright_root=_relative_pattern(entry['copyright_root'], f'{where}.copyright_root')
            if entry.get('copyright_root') else '',
            source_dir=str(entry.get('source_dir') or '').strip().strip('/'),
            evidence=' '.join(str(entry.get('evidence') or '').split()),
            notice=_relative_pattern(entry['notice'], f'{where}.notice')
            if entry.get('notice') else '')
        if any(EVALUATION_ONLY in s for s in (*src.globs, src.copyright_root, src.notice)):
            raise PhotoConfigError(f'{where}: {EVALUATION_ONLY} is reserved for evaluation')
        sources.append(src)
    names = [s.name for s in sources]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise PhotoConfigError(f'{path}: sources listed twice: {", ".join(dup)}')
    return sources


# ------------------------------------------------------------------------ copyright files


@dataclass(frozen=True)
class CopyrightStanza:
    """A ``Files:`` paragraph of a machine-readable (DEP-5) copyright file."""

    patterns: tuple[str, ...]
    copyright: str
    licence: str


def parse_dep5(text: str) -> list[CopyrightStanza] | None:
    """The ``Files:`` stanzas of a DEP-5 copyright file, in order; None if not machine-readable.
    """
    paragraphs: list[dict[str, list[str]]] = []
    current: dict[str, list[str]] = {}
    key = None
    for line in text.splitlines():
        if not line.strip():
            if current:
                paragraphs.append(current)
            current, key = {}, None
            continue
        if line[0] in ' \t':
            if key is not None:
                current[key].append(line.strip())
            continue
        name, sep, value = line.partition(':')
        if not sep:
            key = None
            continue
        key = name.strip().lower()
        current[key] = [value.strip()]
    if current:
        paragraphs.append(current)
    if not paragraphs or 'format' not in paragraphs[0]:
        return None
    stanzas = []
    for para in paragraphs:
        if 'files' not in para:
            continue
        patterns = tuple(' '.join(para['files']).split())
        licence = (para.get('license') or [''])[0].strip()
        holder = '; '.join(x for x in para.get('copyright', []) if x and x != '.')
        stanzas.append(CopyrightStanza(patterns=patterns, copyright=holder, licence=licence))
    return stanzas


def _dep5_match(pattern: str, path: str) -> bool:
    """DEP-5 ``Files:`` matching: ``*`` any characters (``/`` too), ``?`` one, else literal."""
    regex = ''.join('.*' if c == '*' else '.' if c == '?' else re.escape(c) for c in pattern)
    return re.fullmatch(regex, path) is not None


def stanza_for(stanzas: Sequence[CopyrightStanza], source_path: str) -> CopyrightStanza | None:
    """The stanza governing ``source_path``: the last one with a matching pattern (DEP-5)."""
    found = None
    for st in stanzas:
        if any(_dep5_match(p, source_path) for p in st.patterns):
            found = st
    return found


def licence_declared(licence: str, declared: str) -> bool:
    """``licence`` (e.g. ``GPL-2+``) is named as a whole word in the declared licence text."""
    return re.search(r'(?<![\w.+-])' + re.escape(licence) + r'(?![\w.+-])', declared) is not None


# -------------------------------------------------------------------------------- images


def textured_fraction(bgr: np.ndarray) -> float:
    """Fraction of 16x16 px blocks whose grey-level std is >= 4 (at 640 px on the long side)."""
    gray = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY) if bgr.ndim == 3 else bgr
    h, w = gray.shape[:2]
    s = TEXTURE_LONG_SIDE_PX / max(h, w)
    if s < 1.0:
        gray = cv2.resize(gray, (max(1, round(w * s)), max(1, round(h * s))),
                          interpolation=cv2.INTER_AREA)
    b = TEXTURE_BLOCK_PX
    H, W = gray.shape[0] // b * b, gray.shape[1] // b * b
    if H == 0 or W == 0:
        return 0.0
    blocks = gray[:H, :W].astype(np.float32).reshape(H // b, b, W // b, b)
    return float((blocks.std(axis=(1, 3)) >= TEXTURE_MIN_STD).mean())


@dataclass(frozen=True)
class ConvertedImage:
    data: bytes
    original_size: tuple[int, int]  # (width, height) px as decoded (EXIF orientation applied)
    size: tuple[int, int]           # (width, height) px written
    textured: float


def convert_image(path: Path, max_side: int, quality: int) -> ConvertedImage | None:
    """Decode ``path`` as 8-bit BGR, downscale to ``max_side`` px, encode as JPEG; None if
    unreadable."""
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None or bgr.size == 0:
        return None
    h, w = bgr.shape[:2]
    if max(w, h) > max_side:
        s = max_side / max(w, h)
        tw, th = max(1, round(w * s)), max(1, round(h * s))
        out = cv2.resize(bgr, (tw, th), interpolation=cv2.INTER_AREA)
    else:
        out = bgr
    ok, buf = cv2.imencode('.jpg', out, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        return None
    return ConvertedImage(data=buf.tobytes(), original_size=(w, h),
                          size=(out.shape[1], out.shape[0]), textured=textured_fraction(out))


def _sanitize(text: str) -> str:
    return re.sub(r'[^A-Za-z0-9._+-]+', '_', text).strip('_') or 'image'


def output_stems(paths: Sequence[str]) -> dict[str, str]:
    """A unique file stem per path: its own stem, or, for stems that several paths share, the
    path components that tell them apart joined to it (``BytheWater_2560x1600``)."""
    stems = {p: _sanitize(Path(p).stem) for p in paths}
    out: dict[str, str] = {}
    by_stem: dict[str, list[str]] = {}
    for p, s in stems.items():
        by_stem.setdefault(s, []).append(p)
    for s, group in by_stem.items():
        if len(group) == 1:
            out[group[0]] = s
            continue
        parts = [Path(p).parent.parts for p in group]
        depth = max(len(x) for x in parts)
        padded = [x + ('',) * (depth - len(x)) for x in parts]
        keep = [i for i in range(depth) if len({x[i] for x in padded}) > 1]
        for p, x in zip(group, padded):
            out[p] = '_'.join([_sanitize(x[i]) for i in keep if x[i]] + [s])
    seen: dict[str, int] = {}
    for p in sorted(out):
        s = out[p]
        seen[s] = seen.get(s, 0) + 1
        if seen[s] > 1:
            out[p] = f'{s}_{seen[s]}'
    return out


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, 'rb') as f:
        for chunk in iter(lambda: f.read(1 << 20), b''):
            h.update(chunk)
    return h.hexdigest()


# ---------------------------------------------------------------------------- confinement


class OutDir:
    """The output directory; every path handed out resolves inside it."""

    def __init__(self, out: Path) -> None:
        out = Path(out)
        if out.exists() and not out.is_dir():
            raise OutputConfinementError(f'--out {out} exists and is not a directory')
        try:
            out.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise OutputConfinementError(f'cannot create --out {out}: '
                                         f'{exc.strerror or exc}') from exc
        self.root = out
        self.real = out.resolve()

    def path(self, *parts: str, directory: bool = False) -> Path:
        """``OUT/<parts>``; refused if it (or a symlink on the way) leads out of OUT.
        ``directory``: create it."""
        p = self.root.joinpath(*parts)
        real = p.resolve()
        if real != self.real and not real.is_relative_to(self.real):
            raise OutputConfinementError(f'{p} leads out of --out {self.root} (to {real}): '
                                         'refusing to write there')
        if directory:
            if p.exists() and not p.is_dir():
                raise OutputConfinementError(f'{p} exists and is not a directory')
            p.mkdir(parents=True, exist_ok=True)
        return p

    def write_bytes(self, rel_dir: str, name: str, data: bytes) -> Path:
        """Write ``OUT/rel_dir/name`` atomically (temporary file + rename)."""
        target = self.path(rel_dir, name)
        tmp = self.path(rel_dir, f'.{name}.tmp')
        tmp.write_bytes(data)
        os.replace(tmp, target)
        return target


# ------------------------------------------------------------------------------ fetching


def _run(cmd: Sequence[str], cwd: Path | None = None) -> subprocess.CompletedProcess:
    try:
        return subprocess.run(list(cmd), cwd=cwd, capture_output=True, text=True,
                              timeout=_COMMAND_TIMEOUT_S)
    except FileNotFoundError as exc:
        raise SourceError(f'{cmd[0]} not found (a Debian system with dpkg and apt is '
                          'needed)') from exc
    except subprocess.TimeoutExpired as exc:
        raise SourceError(f'{" ".join(cmd[:3])} timed out after {_COMMAND_TIMEOUT_S} s') from exc


def _last_error(proc: subprocess.CompletedProcess) -> str:
    lines = [ln.strip() for ln in (proc.stderr or '').splitlines() if ln.strip()]
    errors = [ln for ln in lines if ln.startswith(('E:', 'dpkg-deb:', 'tar:'))]
    return ' '.join((errors or lines or [f'exit status {proc.returncode}'])[-1].split())


def _find_deb(folder: Path, package: str) -> Path | None:
    found = sorted(p for p in folder.glob(f'{globmod.escape(package)}_*.deb')
                   if p.is_file() and not p.is_symlink())
    if len(found) > 1:
        raise PackageDownloadError(f'several .deb files for {package} in {folder}: '
                                   f'{", ".join(p.name for p in found)}')
    return found[0] if found else None


def _apt_download(package: str, dest: Path) -> Path:
    """``apt-get download PACKAGE`` into ``dest``; the .deb's path."""
    proc = _run(['apt-get', 'download', package], cwd=dest)
    if proc.returncode != 0:
        raise PackageDownloadError(f'apt-get download {package} failed: {_last_error(proc)}')
    deb = _find_deb(dest, package)
    if deb is None:
        raise PackageDownloadError(f'apt-get download {package} left no {package}_*.deb')
    return deb


def _deb_fields(deb: Path) -> dict[str, str]:
    proc = _run(['dpkg-deb', '-f', str(deb), 'Package', 'Version'])
    if proc.returncode != 0:
        raise DebFormatError(f'{deb.name} is not a readable .deb: {_last_error(proc)}')
    fields = {}
    for line in proc.stdout.splitlines():
        k, sep, v = line.partition(':')
        if sep:
            fields[k.strip()] = v.strip()
    return fields


def _unpack(deb: Path, target: Path) -> None:
    if target.exists():
        shutil.rmtree(target)
    target.mkdir(parents=True)
    proc = _run(['dpkg-deb', '-x', str(deb), str(target)])
    if proc.returncode != 0:
        raise DebFormatError(f'dpkg-deb -x {deb.name} failed: {_last_error(proc)}')


def _regular_inside(path: Path, root: Path) -> bool:
    """A regular file, not a symlink, whose real path lies inside ``root``."""
    if path.is_symlink() or not path.is_file():
        return False
    real = path.resolve()
    return real.is_relative_to(root.resolve())


def _match_globs(root: Path, globs: Sequence[str]) -> list[Path]:
    found: dict[str, Path] = {}
    for g in globs:
        for hit in globmod.glob(g, root_dir=root):
            p = root / hit
            if _regular_inside(p, root):
                found[Path(hit).as_posix()] = p
    return [found[k] for k in sorted(found)]


# -------------------------------------------------------------------------------- records


@dataclass
class SourceResult:
    """What one source contributed (kept in ``OUT/cache/done/<name>.json``)."""

    package: str
    version: str
    licence: str
    fingerprint: str
    records: list[dict[str, Any]] = field(default_factory=list)
    skipped: list[dict[str, str]] = field(default_factory=list)


@dataclass
class CollectionSummary:
    """Outcome of a run: per-source results (collected or skipped as finished) and failures."""

    out: Path
    manifest: Path
    results: list[SourceResult]
    failures: dict[str, str]
    reused: list[str]
    seconds: float

    @property
    def total(self) -> int:
        return sum(len(r.records) for r in self.results)


@dataclass(frozen=True)
class CollectOptions:
    """Output options: long side (px), JPEG quality, and the two measured filters."""

    max_side: int = 1280
    quality: int = 92
    min_textured: float = 0.25
    min_side: int = 160

    def check(self) -> None:
        if self.max_side < 16:
            raise PhotoConfigError(f'--max-side must be >= 16 px, got {self.max_side}')
        if not 1 <= self.quality <= 100:
            raise PhotoConfigError(f'--quality must be in 1..100, got {self.quality}')
        if not 0.0 <= self.min_textured <= 1.0:
            raise PhotoConfigError(f'--min-textured must be in [0, 1], got {self.min_textured}')
        if self.min_side < 0:
            raise PhotoConfigError(f'--min-side must be >= 0 px, got {self.min_side}')


def _fingerprint(source: PhotoSource, opts: CollectOptions) -> str:
    blob = json.dumps({'format': FORMAT_VERSION, 'source': asdict(source),
                       'options': asdict(opts)}, sort_keys=True)
    return _sha256(blob.encode())


def _load_done(out: OutDir, source: PhotoSource, fingerprint: str) -> SourceResult | None:
    """The finished result of ``source`` if it matches ``fingerprint`` and its files are intact.
    """
    path = out.path('cache', 'done', f'{source.name}.json')
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text(encoding='utf-8'))
        result = SourceResult(**data)
    except (OSError, ValueError, TypeError):
        return None
    if result.fingerprint != fingerprint:
        return None
    for rec in result.records:
        f = out.path(rec['file'])
        if not f.is_file() or f.is_symlink() or _file_sha256(f) != rec['sha256']:
            return None
    return result


def _previous_files(out: OutDir, source: PhotoSource) -> list[str]:
    path = out.path('cache', 'done', f'{source.name}.json')
    try:
        return [r['file'] for r in json.loads(path.read_text(encoding='utf-8'))['records']]
    except (OSError, ValueError, KeyError, TypeError):
        return []


def _wheel_base(module: str) -> Path:
    try:
        spec = importlib.util.find_spec(module)
    except (ImportError, ValueError):
        spec = None
    if spec is None or not spec.submodule_search_locations:
        raise SourceError(f'module {module} is not installed (see requirements.txt)')
    return Path(list(spec.submodule_search_locations)[0])


def _wheel_version_and_text(module: str) -> tuple[str, str]:
    """Version of the distribution providing ``module`` and its licence metadata as text."""
    dists = importlib.metadata.packages_distributions().get(module) or [module]
    for dist in dists:
        try:
            meta = importlib.metadata.metadata(dist)
        except importlib.metadata.PackageNotFoundError:
            continue
        text = '\n'.join([meta.get('License') or '', meta.get('License-Expression') or '',
                          *(meta.get_all('Classifier') or [])])
        return str(meta.get('Version') or ''), text
    return '', ''


def _collect_source(source: PhotoSource, out: OutDir, opts: CollectOptions,
                    deb_dir: Path | None, seen: dict[str, str]) -> SourceResult:
    """Collect the images of one source into ``OUT/images``."""
    fingerprint = _fingerprint(source, opts)
    unpacked: Path | None = None
    if source.is_wheel:
        base = _wheel_base(source.name)
        from semfeat_ros.model.data import resolve_photo_paths
        paths = [p for p in resolve_photo_paths([f'module:{source.name}/{g}'
                                                 for g in source.globs])
                 if _regular_inside(p, base)]
        version, text = _wheel_version_and_text(source.name)
        if source.notice:
            try:
                text = (base / source.notice).read_text(encoding='utf-8', errors='replace')
            except OSError as exc:
                raise CopyrightError(f'notice {source.notice} of {source.name} unreadable: '
                                     f'{exc.strerror or exc}') from exc
        if source.evidence and source.evidence not in ' '.join(text.split()):
            raise CopyrightError(f'{source.notice or "the wheel metadata"} of {source.name} '
                                 f'does not state {source.evidence!r}')
        stanzas = None
        root = base
        inner = {p: f'{source.name}/{p.relative_to(base).as_posix()}' for p in paths}
    else:
        if deb_dir is not None:
            deb = _find_deb(deb_dir, source.package)
            if deb is None:
                raise PackageDownloadError(f'no {source.package}_*.deb in --deb-dir {deb_dir}')
        else:
            debs = out.path('cache', 'debs', directory=True)
            deb = _find_deb(debs, source.package) or _apt_download(source.package, debs)
        fields = _deb_fields(deb)
        if fields.get('Package') != source.package:
            raise DebFormatError(f'{deb.name} holds package {fields.get("Package")!r}, not '
                                 f'{source.package}')
        version = fields.get('Version', '')
        unpacked = out.path('cache', 'unpacked', source.package)
        out.path('cache', 'unpacked', directory=True)
        _unpack(deb, unpacked)
        root = unpacked
        copyright_file = root / 'usr/share/doc' / source.package / 'copyright'
        if not _regular_inside(copyright_file, root):
            raise CopyrightError(f'{source.package} has no usr/share/doc/{source.package}/'
                                 'copyright file')
        text = copyright_file.read_text(encoding='utf-8', errors='replace')
        stanzas = parse_dep5(text)
        if stanzas is None and not source.evidence:
            raise CopyrightError(f'the copyright file of {source.package} is not '
                                 'machine-readable: photos.yaml must give "evidence"')
        if source.evidence and source.evidence not in ' '.join(text.split()):
            raise CopyrightError(f'the copyright file of {source.package} does not state '
                                 f'{source.evidence!r}')
        paths = _match_globs(root, source.globs)
        inner = {p: p.relative_to(root).as_posix() for p in paths}
    result = SourceResult(package=source.package, version=version, licence=source.licence,
                          fingerprint=fingerprint)
    stems = output_stems([inner[p] for p in paths])
    out.path('images', directory=True)
    try:
        for p in paths:
            rel = inner[p]
            licence, holder = source.licence, ''
            if stanzas is not None:
                cr_root = source.copyright_root
                local = rel
                if cr_root and (rel == cr_root or rel.startswith(cr_root.rstrip('/') + '/')):
                    local = rel[len(cr_root.rstrip('/')) + 1:]
                    local = f'{source.source_dir}/{local}' if source.source_dir else local
                st = stanza_for(stanzas, local)
                if st is None:
                    result.skipped.append({'path': rel, 'reason': 'no Files: stanza of the '
                                           f'copyright file covers {local}'})
                    continue
                if not licence_declared(st.licence, source.licence):
                    result.skipped.append({'path': rel, 'reason': f'licence {st.licence!r} is '
                                           'not declared in photos.yaml'})
                    continue
                licence, holder = st.licence, st.copyright
            source_sha = _file_sha256(p)
            if source_sha in seen:
                result.skipped.append({'path': rel, 'reason': f'same file as {seen[source_sha]}'})
                continue
            img = convert_image(p, opts.max_side, opts.quality)
            if img is None:
                result.skipped.append({'path': rel, 'reason': 'unreadable image'})
                continue
            if min(img.original_size) < opts.min_side:
                result.skipped.append({'path': rel, 'reason': f'short side '
                                       f'{min(img.original_size)} px < {opts.min_side} px'})
                continue
            if img.textured < opts.min_textured:
                result.skipped.append({'path': rel, 'reason': f'textured fraction '
                                       f'{img.textured:.2f} < {opts.min_textured}'})
                continue
            name = f'{_sanitize(source.name)}__{stems[rel]}.jpg'
            out.write_bytes('images', name, img.data)
            seen[source_sha] = f'{source.package}:{rel}'
            result.records.append({
                'file': f'images/{name}', 'package': source.package, 'version': version,
                'path': rel, 'licence': licence, 'copyright': holder,
                'original_size': list(img.original_size), 'size': list(img.size),
                'sha256': _sha256(img.data), 'source_sha256': source_sha,
                'textured_fraction': round(img.textured, 3)})
    finally:
        if unpacked is not None and unpacked.exists():
            shutil.rmtree(unpacked, ignore_errors=True)
    if not result.records:
        reasons = '; '.join(f'{s["path"]}: {s["reason"]}' for s in result.skipped[:3])
        raise NoImagesError(f'{source.package}: no image collected ({len(paths)} matched the '
                            f'globs{"; " + reasons if reasons else ""})')
    return result


def main(out: Path, config: Path | None = None, *, deb_dir: Path | None = None,
         only: Sequence[str] = (), options: CollectOptions | None = None,
         progress: bool = True, report: Callable[[str], None] | None = None
         ) -> CollectionSummary:
    """Collect the photographs of ``config`` (default: the shipped ``photos.yaml``) into ``out``.

    Args:
        out: output directory (created); everything written stays inside it.
        config: the list of sources.
        deb_dir: folder of already downloaded .deb files used instead of ``apt-get download``.
        only: names of the sources to (re)collect now; the others' finished results are kept.
        options: output size (px), JPEG quality and filters.
        progress: show a tqdm bar.
        report: receives one line per failed source (default: stderr).

    Returns:
        The summary; ``OUT/manifest.json`` holds the records of every collected source.
    """
    t0 = time.monotonic()
    opts = options or CollectOptions()
    opts.check()
    if config is None:
        from semfeat_ros.paths import config_path
        config = config_path('photos.yaml')
    sources = load_sources(Path(config))
    unknown = sorted(set(only) - {s.name for s in sources})
    if unknown:
        raise PhotoConfigError(f'--only: no source named {", ".join(unknown)} in {config}')
    if deb_dir is not None and not Path(deb_dir).is_dir():
        raise PhotoConfigError(f'--deb-dir {deb_dir} is not a directory')
    outdir = OutDir(Path(out))
    for sub in ('images', 'cache', 'cache/done'):
        outdir.path(sub, directory=True)
    emit = report or (lambda line: tqdm.write(line, file=sys.stderr))
    results: list[SourceResult] = []
    failures: dict[str, str] = {}
    reused: list[str] = []
    seen: dict[str, str] = {}
    bar = tqdm(sources, desc=PROG, unit='source', disable=not progress, file=sys.stderr)
    for source in bar:
        bar.set_postfix_str(source.name)
        done = _load_done(outdir, source, _fingerprint(source, opts))
        if done is not None and (not only or source.name not in only):
            results.append(done)
            reused.append(source.name)
            for rec in done.records:
                seen.setdefault(rec.get('source_sha256', rec['sha256']), rec['file'])
            continue
        if only and source.name not in only:
            continue
        try:
            result = _collect_source(source, outdir, opts, deb_dir, seen)
        except (SourceError, OSError, cv2.error) as exc:
            failures[source.package] = error_line(exc)
            emit(f'{PROG}: {source.package}: {error_line(exc)}')
            continue
        keep = {r['file'] for r in result.records}
        for old in _previous_files(outdir, source):
            if old not in keep:
                stale = outdir.path(old)
                if stale.is_file() and not stale.is_symlink():
                    stale.unlink()
        outdir.write_bytes('cache/done', f'{source.name}.json',
                           json.dumps(asdict(result), indent=1).encode())
        results.append(result)
    bar.close()
    manifest = {
        'tool': PROG, 'config': str(config),
        'options': asdict(opts),
        'licence_note': 'training only; the photographs are never committed, the list of '
                        'sources with their licences is (config/photos.yaml)',
        'sources': [{'package': r.package, 'version': r.version, 'licence': r.licence,
                     'images': len(r.records), 'skipped': r.skipped} for r in results],
        'failed': [{'package': k, 'error': v} for k, v in failures.items()],
        'images': [rec for r in results for rec in r.records],
    }
    path = outdir.write_bytes('.', 'manifest.json',
                              (json.dumps(manifest, indent=1) + '\n').encode())
    return CollectionSummary(out=Path(out), manifest=path, results=results, failures=failures,
                             reused=reused, seconds=time.monotonic() - t0)


def build_parser() -> argparse.ArgumentParser:
    p = OneLineParser.for_tool(PROG, __doc__)
    p.add_argument('--out', type=Path, required=True, help='output directory (images/, '
                   'manifest.json, cache/)')
    p.add_argument('--config', type=Path, default=None,
                   help='list of sources (default: the shipped config/photos.yaml)')
    p.add_argument('--deb-dir', type=Path, default=None, help='folder of already downloaded '
                   '.deb files to use instead of apt-get download')
    p.add_argument('--only', action='append', default=[], metavar='NAME',
                   help='(re)collect only this source (repeatable; Debian package or module '
                   'name); the others keep their finished results')
    p.add_argument('--max-side', type=int, default=1280, help='long side of the output (px)')
    p.add_argument('--quality', type=int, default=92, help='JPEG quality (1-100)')
    p.add_argument('--min-textured', type=float, default=0.25,
                   help='drop images with a smaller fraction of textured 16x16 px blocks')
    p.add_argument('--min-side', type=int, default=160,
                   help='drop images whose short side is smaller (px)')
    p.add_argument('--quiet', action='store_true', help='no progress bar, no summary')
    return p


def cli(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    opts = CollectOptions(max_side=args.max_side, quality=args.quality,
                          min_textured=args.min_textured, min_side=args.min_side)
    try:
        s = main(args.out, args.config, deb_dir=args.deb_dir, only=args.only, options=opts,
                 progress=not args.quiet)
    except (PhotoToolError, OSError) as exc:
        print(f'{PROG}: error: {error_line(exc)}', file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f'{PROG}: interrupted', file=sys.stderr)
        return 130
    if not args.quiet:
        for r in s.results:
            tag = ' (finished earlier)' if r.package.removeprefix('module:') in s.reused else ''
            print(f'{r.package} {r.version}: {len(r.records)} photos, {r.licence}{tag}')
    print(f'{PROG}: {s.total} photos from {len(s.results)} sources in {s.out / "images"} '
          f'({len(s.failures)} failed), manifest {s.manifest}, {s.seconds:.1f} s')
    if s.total == 0:
        print(f'{PROG}: error: nothing was collected', file=sys.stderr)
        return 1
    return 0


if __name__ == '__main__':
    sys.exit(cli())
