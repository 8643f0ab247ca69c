"""The shared configuration merge and value checks (semfeat_ros.conf)."""
from __future__ import annotations

import copy
import math

import pytest

from semfeat_ros.conf import check_choice, check_fraction, check_int_min, check_number, merge_conf
from semfeat_ros.mapping.errors import MapperConfigError
from semfeat_ros.matching.errors import MatchingConfigError
from semfeat_ros.model.errors import ModelConfigError

DEFAULT = {
    'rate': 1.5,
    'labels': ['road', 'wall'],
    'tracking': {'max_missed': 3, 'gate': {'px': 4.0, 'deg': 2.0}},
    'mix': {'synthetic': 0.5, 'drive': 0.5},
}


def test_merge_overrides_nested_keys_and_keeps_the_rest() -> None:
    out = merge_conf(DEFAULT, {'tracking': {'gate': {'px': 8.0}}, 'rate': 2},
                     MatchingConfigError)
    assert out['rate'] == 2
    assert out['tracking'] == {'max_missed': 3, 'gate': {'px': 8.0, 'deg': 2.0}}
    assert out['labels'] == ['road', 'wall'] and out['mix'] == DEFAULT['mix']
    assert merge_conf(DEFAULT, None, MatchingConfigError) == DEFAULT
    assert merge_conf(DEFAULT, {'tracking': None}, MatchingConfigError) == DEFAULT


def test_unknown_key_at_depth_raises_the_callers_class_with_the_dotted_name() -> None:
    with pytest.raises(MatchingConfigError,
                       match=r'unknown config key conf\.tracking\.gate\.pxx; known keys: deg, px'):
        merge_conf(DEFAULT, {'tracking': {'gate': {'pxx': 1.0}}}, MatchingConfigError,
                   name='conf')
    with pytest.raises(MapperConfigError, match=r'unknown mapping config key b, z;'):
        merge_conf(DEFAULT, {'z': 1, 'b': 2, 'rate': 1.0}, MapperConfigError,
                   what='mapping config key')
    with pytest.raises(ModelConfigError, match=r'tracking: expected a mapping, got int'):
        merge_conf(DEFAULT, {'tracking': 3}, ModelConfigError)


def test_opaque_values_are_replaced_not_merged() -> None:
    out = merge_conf(DEFAULT, {'mix': {'photo': 1.0}}, ModelConfigError, opaque=('mix',))
    assert out['mix'] == {'photo': 1.0}
    with pytest.raises(ModelConfigError, match=r'unknown config key data\.mix\.photo'):
        merge_conf(DEFAULT, {'mix': {'photo': 1.0}}, ModelConfigError, name='data')
    nested = merge_conf(DEFAULT, {'tracking': {'gate': {'m': 1.0}}}, ModelConfigError,
                        opaque=('tracking.gate',))
    assert nested['tracking'] == {'max_missed': 3, 'gate': {'m': 1.0}}


def test_defaults_and_overrides_are_not_mutated_or_shared() -> None:
    before = copy.deepcopy(DEFAULT)
    override = {'tracking': {'gate': {'px': 8.0}}, 'labels': ['pillar']}
    out = merge_conf(DEFAULT, override, MatchingConfigError)
    out['tracking']['gate']['deg'] = 99.0
    out['labels'].append('sky')
    out['mix']['drive'] = 0.0
    assert DEFAULT == before
    assert override == {'tracking': {'gate': {'px': 8.0}}, 'labels': ['pillar']}
    again = merge_conf(DEFAULT, None, MatchingConfigError)
    again['labels'].append('x')
    assert DEFAULT['labels'] == ['road', 'wall']


def test_check_number() -> None:
    check_number(0.5, 'a.b', MatchingConfigError, 0.0, 1.0)
    check_number(3.0, 'a.b', MatchingConfigError, 1, None, integer=True)
    check_number(-1e9, 'a.b', MatchingConfigError)
    with pytest.raises(MatchingConfigError, match=r'a\.b must be a number in \(0\.0, 1\.0\]'):
        check_number(0.0, 'a.b', MatchingConfigError, 0.0, 1.0, lo_open=True)
    with pytest.raises(MatchingConfigError, match=r'a\.b must be a number in \[0\.0, 1\.0\]'):
        check_number(1.01, 'a.b', MatchingConfigError, 0.0, 1.0)
    with pytest.raises(MatchingConfigError, match='must be an integer'):
        check_number(2.5, 'a.b', MatchingConfigError, integer=True)
    for bad in (True, '1', None, math.nan):
        with pytest.raises(MapperConfigError, match='k'):
            check_number(bad, 'k', MapperConfigError, 0.0)


def test_check_int_min_choice_fraction() -> None:
    check_int_min(1, 'n', MapperConfigError, 1)
    for bad in (0, 1.0, True, '2'):
        with pytest.raises(MapperConfigError, match='n must be an integer >= 1'):
            check_int_min(bad, 'n', MapperConfigError, 1)
    check_choice('huber', 'kernel', ModelConfigError, ('huber', 'cauchy'))
    with pytest.raises(ModelConfigError, match=r"kernel must be one of \('huber', 'cauchy'\)"):
        check_choice('tukey', 'kernel', ModelConfigError, ('huber', 'cauchy'))
    check_fraction(0, 'f', ModelConfigError)
    check_fraction(1.0, 'f', ModelConfigError)
    for bad in (-0.1, 1.5, math.nan, False, None):
        with pytest.raises(ModelConfigError, match=r'f must be a number in \[0, 1\]'):
            check_fraction(bad, 'f', ModelConfigError)
