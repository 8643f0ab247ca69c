"""semfeat-photos on .deb files built here with dpkg-deb (the package registry is never asked)."""
from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
import shutil
import subprocess

from conftest import REPO
import cv2
import numpy as np
import pytest
import yaml

from semfeat_ros.tools import photos

pytestmark = pytest.mark.skipif(shutil.which('dpkg-deb') is None, reason='needs dpkg-deb')

PKG = 'semfeat-fake-photos'
COPYRIGHT = """Format: https://www.debian.org/doc/packaging-manuals/copyright-format/1.0/
Upstream-Name: fake

Files: *
Copyright: 2024, Somebody
License: CC0-1.0

Files: pics/big/*
       pics/other/*
Copyright: 2023, A Photographer
License: CC-BY-4.0
"""


def textured(width: int, height: int, seed: int) -> np.ndarray:
    """Smoothed noise: every 16x16 px block has a grey-level std well above 4."""
    rng = np.random.default_rng(seed)
    img = rng.integers(0, 256, (height, width, 3), dtype=np.uint8)
    return cv2.GaussianBlur(img, (0, 0), 1.0)


def build_deb(folder: Path, package: str, files: dict[str, bytes | Path],
              copyright_text: str | None = COPYRIGHT, version: str = '1.0-1') -> Path:
    """A real .deb (dpkg-deb --build) holding ``files`` (bytes, or a Path: a symlink to it)."""
    root = folder / f'{package}-root'
    (root / 'DEBIAN').mkdir(parents=True)
    (root / 'DEBIAN' / 'control').write_text(
        f'Package: {package}\nVersion: {version}\nArchitecture: all\n'
        'Maintainer: Test <test@example.com>\nDescription: photos for a test\n')
    if copyright_text is not None:
        doc = root / 'usr/share/doc' / package
        doc.mkdir(parents=True)
        (doc / 'copyright').write_text(copyright_text)
    for rel, content in files.items():
        p = root / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        if isinstance(content, Path):
            p.symlink_to(content)
        else:
            p.write_bytes(content)
    deb = folder / f'{package}_{version}_all.deb'
    subprocess.run(['dpkg-deb', '--root-owner-group', '-Znone', '--build', str(root), str(deb)],
                   check=True, capture_output=True)
    shutil.rmtree(root)
    return deb


def encode(img: np.ndarray, ext: str) -> bytes:
    ok, buf = cv2.imencode(ext, img)
    assert ok
    return buf.tobytes()


@pytest.fixture
def debs(tmp_path: Path) -> Path:
    folder = tmp_path / 'debs'
    folder.mkdir()
    outside = tmp_path / 'outside.jpg'
    outside.write_bytes(encode(textured(400, 300, 9), '.jpg'))
    build_deb(folder, PKG, {
        'usr/share/fakepics/big/wide.png': encode(textured(2000, 1000, 1), '.png'),
        'usr/share/fakepics/small.jpg': encode(textured(300, 200, 2), '.jpg'),
        'usr/share/fakepics/flat.png': encode(np.full((300, 400, 3), 128, np.uint8), '.png'),
        'usr/share/fakepics/tiny.png': encode(textured(120, 90, 3), '.png'),
        'usr/share/fakepics/escape.jpg': outside,  # symlink out of the package: never read
        'usr/share/fakepics/alias.jpg': Path('small.jpg'),  # symlink inside: skipped too
    })
    (folder / 'semfeat-broken-photos_1.0_all.deb').write_bytes(b'!<arch>\nthis is no deb\n')
    return folder


def write_config(path: Path, *sources: dict) -> Path:
    path.write_text(yaml.safe_dump({'sources': list(sources)}))
    return path


FAKE_SOURCE = {'package': PKG, 'licence': 'CC0-1.0, CC-BY-4.0 (per file)',
               'copyright_root': 'usr/share/fakepics', 'source_dir': 'pics',
               'globs': ['usr/share/fakepics/*.jpg', 'usr/share/fakepics/*.png',
                         'usr/share/fakepics/big/*.png']}
BROKEN_SOURCE = {'package': 'semfeat-broken-photos', 'licence': 'CC0-1.0',
                 'globs': ['usr/share/x/*.jpg']}


@pytest.fixture
def no_registry(monkeypatch: pytest.MonkeyPatch) -> None:
    def refuse(package: str, dest: Path) -> Path:
        raise AssertionError(f'the registry was asked for {package}')
    monkeypatch.setattr(photos, '_apt_download', refuse)


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_collects_images_with_licences_and_sizes(tmp_path, debs, no_registry, capsys) -> None:
    cfg = write_config(tmp_path / 'photos.yaml', FAKE_SOURCE)
    out = tmp_path / 'out'
    assert photos.cli(['--out', str(out), '--config', str(cfg), '--deb-dir', str(debs),
                       '--quiet']) == 0
    manifest = json.loads((out / 'manifest.json').read_text())
    recs = {r['path']: r for r in manifest['images']}
    assert sorted(recs) == ['usr/share/fakepics/big/wide.png', 'usr/share/fakepics/small.jpg']
    wide, small = recs['usr/share/fakepics/big/wide.png'], recs['usr/share/fakepics/small.jpg']
    assert wide['licence'] == 'CC-BY-4.0' and wide['copyright'] == '2023, A Photographer'
    assert small['licence'] == 'CC0-1.0' and small['copyright'] == '2024, Somebody'
    assert wide['original_size'] == [2000, 1000] and wide['size'] == [1280, 640]
    assert small['original_size'] == [300, 200] and small['size'] == [300, 200]
    for rec in (wide, small):
        assert rec['package'] == PKG and rec['version'] == '1.0-1'
        f = out / rec['file']
        assert f.parent == out / 'images' and f.name.startswith(f'{PKG}__')
        assert sha256(f) == rec['sha256']
        img = cv2.imread(str(f))
        assert f.read_bytes()[:2] == b'\xff\xd8' and [img.shape[1], img.shape[0]] == rec['size']
    assert (out / 'images' / f'{PKG}__wide.jpg').is_file()
    skipped = {s['path']: s['reason'] for s in manifest['sources'][0]['skipped']}
    assert 'textured fraction 0.00' in skipped['usr/share/fakepics/flat.png']
    assert 'short side 90 px' in skipped['usr/share/fakepics/tiny.png']
    for link in ('escape.jpg', 'alias.jpg'):  # symlinks are never followed
        assert f'usr/share/fakepics/{link}' not in set(recs) | set(skipped)
    assert not list((out / 'cache' / 'unpacked').iterdir())  # unpacked tree removed
    assert manifest['failed'] == []
    assert capsys.readouterr().err == ''


def test_second_run_skips_finished_sources(tmp_path, debs, no_registry, monkeypatch) -> None:
    cfg = write_config(tmp_path / 'photos.yaml', FAKE_SOURCE)
    out = tmp_path / 'out'
    args = ['--out', str(out), '--config', str(cfg), '--deb-dir', str(debs), '--quiet']
    assert photos.cli(args) == 0
    stamps = {p.name: p.stat().st_mtime_ns for p in (out / 'images').iterdir()}
    first = json.loads((out / 'manifest.json').read_text())['images']

    def untouched(deb: Path) -> dict:
        raise AssertionError('a finished package was opened again')
    monkeypatch.setattr(photos, '_deb_fields', untouched)
    assert photos.cli(args) == 0
    assert {p.name: p.stat().st_mtime_ns for p in (out / 'images').iterdir()} == stamps
    assert json.loads((out / 'manifest.json').read_text())['images'] == first
    # Other options redo the source: smaller output, same names, no leftovers.
    monkeypatch.undo()
    photos_dir = out / 'images'
    assert photos.cli(args + ['--max-side', '640']) == 0
    recs = json.loads((out / 'manifest.json').read_text())['images']
    assert {r['path']: r['size'] for r in recs}['usr/share/fakepics/big/wide.png'] == [640, 320]
    assert sorted(p.name for p in photos_dir.iterdir()) == sorted(stamps)


def test_broken_deb_is_one_line_and_the_others_go_on(tmp_path, debs, no_registry,
                                                       capsys) -> None:
    cfg = write_config(tmp_path / 'photos.yaml', BROKEN_SOURCE, FAKE_SOURCE)
    out = tmp_path / 'out'
    assert photos.cli(['--out', str(out), '--config', str(cfg), '--deb-dir', str(debs),
                       '--quiet']) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith('semfeat-photos: semfeat-broken-photos: ')
    assert 'not a readable .deb' in err[0]
    manifest = json.loads((out / 'manifest.json').read_text())
    assert [f['package'] for f in manifest['failed']] == ['semfeat-broken-photos']
    assert len(manifest['images']) == 2
    # Alone, the broken package collects nothing: non-zero exit.
    cfg2 = write_config(tmp_path / 'broken.yaml', BROKEN_SOURCE)
    assert photos.cli(['--out', str(tmp_path / 'out2'), '--config', str(cfg2), '--deb-dir',
                       str(debs), '--quiet']) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1] == 'semfeat-photos: error: nothing was collected' and len(err) == 2


def test_missing_deb_and_copyright_problems(tmp_path, debs, no_registry, capsys) -> None:
    build_deb(debs, 'semfeat-nocopyright', {'usr/share/p/a.jpg': encode(textured(400, 300, 4),
                                                                           '.jpg')},
              copyright_text=None)
    build_deb(debs, 'semfeat-freeform', {'usr/share/p/a.jpg': encode(textured(400, 300, 5),
                                                                        '.jpg')},
              copyright_text='These pictures are in the public domain.\n')
    cfg = write_config(
        tmp_path / 'photos.yaml',
        {'package': 'semfeat-absent', 'licence': 'MIT', 'globs': ['*.jpg']},
        {'package': 'semfeat-nocopyright', 'licence': 'MIT', 'globs': ['usr/share/p/*.jpg']},
        {'package': 'semfeat-freeform', 'licence': 'public-domain',
         'globs': ['usr/share/p/*.jpg']},
        dict(FAKE_SOURCE, licence='CC0-1.0'))  # CC-BY-4.0 not declared: wide.png refused
    out = tmp_path / 'out'
    assert photos.cli(['--out', str(out), '--config', str(cfg), '--deb-dir', str(debs),
                       '--quiet']) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 3
    assert 'semfeat-absent: no semfeat-absent_*.deb in --deb-dir' in err[0]
    assert 'semfeat-nocopyright: semfeat-nocopyright has no usr/share/doc/' in err[1]
    assert 'semfeat-freeform: the copyright file of semfeat-freeform is not machine-readable' \
        in err[2]
    manifest = json.loads((out / 'manifest.json').read_text())
    assert [r['path'] for r in manifest['images']] == ['usr/share/fakepics/small.jpg']
    skipped = {s['path']: s['reason'] for s in manifest['sources'][0]['skipped']}
    assert "licence 'CC-BY-4.0' is not declared" in skipped['usr/share/fakepics/big/wide.png']
    # With evidence found in the free-form file the package is accepted.
    cfg = write_config(tmp_path / 'ev.yaml', {
        'package': 'semfeat-freeform', 'licence': 'public-domain',
        'evidence': 'are in the public  domain', 'globs': ['usr/share/p/*.jpg']})
    assert photos.cli(['--out', str(out), '--config', str(cfg), '--deb-dir', str(debs),
                       '--quiet']) == 0
    rec = json.loads((out / 'manifest.json').read_text())['images'][0]
    assert rec['licence'] == 'public-domain' and rec['copyright'] == ''


def test_outputs_stay_inside_out(tmp_path, debs, no_registry, capsys) -> None:
    cfg = write_config(tmp_path / 'photos.yaml', FAKE_SOURCE)
    elsewhere = tmp_path / 'elsewhere'
    elsewhere.mkdir()
    out = tmp_path / 'out'
    out.mkdir()
    (out / 'images').symlink_to(elsewhere)
    assert photos.cli(['--out', str(out), '--config', str(cfg), '--deb-dir', str(debs),
                       '--quiet']) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith('semfeat-photos: error: ')
    assert 'leads out of --out' in err[0]
    assert list(elsewhere.iterdir()) == []
    # A symlinked output file is refused the same way, and the target is left alone.
    (out / 'images').unlink()
    (out / 'images').mkdir()
    victim = elsewhere / 'victim.jpg'
    victim.write_bytes(b'keep')
    (out / 'images' / f'{PKG}__small.jpg').symlink_to(victim)
    assert photos.cli(['--out', str(out), '--config', str(cfg), '--deb-dir', str(debs),
                       '--quiet']) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and err[0].startswith(f'semfeat-photos: {PKG}: ')
    assert 'leads out of --out' in err[0] and victim.read_bytes() == b'keep'
    # --out that is a file: one line, exit 1.
    f = tmp_path / 'afile'
    f.write_text('x')
    assert photos.cli(['--out', str(f), '--config', str(cfg), '--deb-dir', str(debs)]) == 1
    assert capsys.readouterr().err.strip() == \
        f'semfeat-photos: error: --out {f} exists and is not a directory'


def test_wheel_source(tmp_path, capsys) -> None:
    src = {'package': 'module:skimage', 'licence': 'CC0-1.0', 'notice': 'data/_fetchers.py',
           'evidence': 'Creative Commons CC0', 'globs': ['data/brick.png', 'data/gravel.png']}
    cfg = write_config(tmp_path / 'photos.yaml', src)
    out = tmp_path / 'out'
    assert photos.cli(['--out', str(out), '--config', str(cfg), '--quiet']) == 0
    recs = json.loads((out / 'manifest.json').read_text())['images']
    import skimage
    assert [(r['package'], r['path'], r['version']) for r in recs] == [
        ('module:skimage', 'skimage/data/brick.png', skimage.__version__),
        ('module:skimage', 'skimage/data/gravel.png', skimage.__version__)]
    assert all(r['size'] == [512, 512] and r['licence'] == 'CC0-1.0' for r in recs)
    cfg = write_config(tmp_path / 'bad.yaml', dict(src, evidence='GPL-3.0-only'))
    assert photos.cli(['--out', str(tmp_path / 'out2'), '--config', str(cfg), '--quiet']) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert "does not state 'GPL-3.0-only'" in err[0] and len(err) == 2


@pytest.mark.parametrize('entry, message', [
    ({'package': 'visp-images-data', 'licence': 'x', 'globs': ['a']}, 'evaluation sequence'),
    ({'package': 'module:x', 'licence': 'x', 'globs': ['shared/data/real_fisheye_calib/*']},
     'reserved for evaluation'),
    ({'package': 'pkg', 'licence': 'x', 'globs': ['../etc/*']}, 'without ".."'),
    ({'package': 'pkg', 'globs': ['a']}, '"licence" is required'),
    ({'package': 'Bad Name', 'licence': 'x', 'globs': ['a']}, 'invalid package'),
])
def test_bad_config_is_one_line(tmp_path, capsys, entry, message) -> None:
    cfg = write_config(tmp_path / 'photos.yaml', entry)
    assert photos.cli(['--out', str(tmp_path / 'out'), '--config', str(cfg)]) == 1
    err = capsys.readouterr().err.strip()
    assert '\n' not in err and err.startswith('semfeat-photos: error: ') and message in err


def test_shipped_list_covers_the_training_photos() -> None:
    sources = photos.load_sources(REPO / 'config' / 'photos.yaml')
    assert len(sources) >= 10 and all(s.licence for s in sources)
    wheel_patterns = {f'module:{s.name}/{g}' for s in sources if s.is_wheel for g in s.globs}
    train = yaml.safe_load((REPO / 'config' / 'train.yaml').read_text())['data']['photos']
    assert set(train) <= wheel_patterns, set(train) - wheel_patterns
    assert not any(s.package in photos.EXCLUDED_PACKAGES for s in sources)


def test_dep5_parsing_and_names() -> None:
    stanzas = photos.parse_dep5(COPYRIGHT)
    assert [s.licence for s in stanzas] == ['CC0-1.0', 'CC-BY-4.0']
    assert stanzas[1].patterns == ('pics/big/*', 'pics/other/*')
    assert photos.stanza_for(stanzas, 'pics/other/x/y.jpg').licence == 'CC-BY-4.0'  # last wins
    assert photos.stanza_for(stanzas, 'pics/x.jpg').licence == 'CC0-1.0'
    assert photos.parse_dep5('Free text, no format line.\n') is None
    assert photos.licence_declared('GPL-2+', 'GPL-2+') and \
        not photos.licence_declared('GPL-2', 'GPL-2+ only')
    names = photos.output_stems(['w/A/contents/images/2560x1600.jpg',
                                 'w/B/contents/images/2560x1600.jpg', 'w/C/x y.png'])
    assert names == {'w/A/contents/images/2560x1600.jpg': 'A_2560x1600',
                     'w/B/contents/images/2560x1600.jpg': 'B_2560x1600', 'w/C/x y.png': 'x_y'}
    assert os.sep not in ''.join(names.values())
