"""The settings rules (assist_common.settings): types, Rules, relations, --flags and --config precedence."""
from __future__ import annotations

import dataclasses

import pytest

from assist_common.settings import (Rule, SettingsError, check_named, check_settings, exit_error, flag,
                                    load_yaml_settings, parse_settings, setting)


@dataclasses.dataclass
class Demo:
    """A settings object with one field of each kind."""

    rate_hz: float = setting(20.0, gt=0.0, le=200.0)
    count: int = setting(3, ge=1)
    mode: str = setting('a', choices=('a', 'b'))
    name: str = setting('out', file_name=True)
    verbose: bool = False
    weights: tuple[float, ...] = setting((1.0, 2.0), min_len=1, max_len=3, ge=0.0)

    def check_relations(self) -> None:
        """count may not exceed the rate."""
        if self.count > self.rate_hz:
            raise SettingsError(f'{flag("count")} must not exceed {flag("rate_hz")}')


def test_defaults_pass():
    check_settings(Demo())


@pytest.mark.parametrize('changes, words', [
    ({'rate_hz': 0.0}, '--rate-hz must be > 0'),
    ({'rate_hz': float('nan')}, '--rate-hz must be a finite number'),
    ({'count': 1.5}, '--count must be an integer'),
    ({'count': True}, '--count must be an integer'),
    ({'mode': 'c'}, '--mode must be one of a, b'),
    ({'name': '../x'}, "--name must be a plain name"),
    ({'name': 'a\0b'}, '--name must not contain a NUL character'),
    ({'verbose': 'yes'}, '--verbose must be true or false'),
    ({'weights': ()}, '--weights needs at least 1 value(s)'),
    ({'weights': (1.0, 2.0, 3.0, 4.0)}, '--weights takes at most 3 value(s)'),
    ({'weights': (1.0, -1.0)}, '--weights items must be >= 0'),
    ({'count': 30}, '--count must not exceed --rate-hz'),
])
def test_each_rule_is_one_line_naming_the_flag(changes, words):
    with pytest.raises(SettingsError) as err:
        check_settings(dataclasses.replace(Demo(), **changes))
    assert words in str(err.value) and '\n' not in str(err.value)


@dataclasses.dataclass
class Flags:
    """Scalar fields only: what parse_settings turns into --flags."""

    rate_hz: float = setting(20.0, gt=0.0)
    count: int = setting(3, ge=1)
    mode: str = setting('a', choices=('a', 'b'))
    verbose: bool = False


def test_rule_problem_on_scalars():
    assert Rule(ge=0.0).problem(-1) == 'must be >= 0'
    assert Rule(lt=1.0).problem(0.5) is None
    assert Rule(nonempty=True).problem('') == 'must not be empty'


def test_precedence_default_yaml_flag(tmp_path):
    y = tmp_path / 'c.yaml'
    y.write_text('rate_hz: 50\ncount: 4\n')
    cfg, _ = parse_settings(Flags, 'demo', ['--config', str(y), '--count', '5', '--verbose'])
    assert (cfg.rate_hz, cfg.count, cfg.mode, cfg.verbose) == (50.0, 5, 'a', True)
    assert load_yaml_settings(Flags, y) == {'rate_hz': 50, 'count': 4}


def test_unknown_yaml_key_and_bad_flag_exit_2(tmp_path, capsys):
    y = tmp_path / 'c.yaml'
    y.write_text('nope: 1\n')
    with pytest.raises(SystemExit) as ex:
        parse_settings(Flags, 'demo', ['--config', str(y)])
    assert ex.value.code == 2 and "unknown Flags setting(s) ['nope']" in capsys.readouterr().err
    with pytest.raises(SystemExit) as ex:
        parse_settings(Flags, 'demo', ['--mode', 'z'])
    assert ex.value.code == 2 and '--mode must be one of a, b' in capsys.readouterr().err


def test_exit_error_is_one_line(capsys):
    with pytest.raises(SystemExit) as ex:
        exit_error('prog', FileNotFoundError(2, 'No such file or directory', '/x/y'), 1)
    assert ex.value.code == 1
    assert capsys.readouterr().err == "prog: error: [Errno 2] No such file or directory: '/x/y'\n"


def test_check_named_names_the_field_as_code_and_config_files_do():
    with pytest.raises(SettingsError, match=r'^rate_hz must be <= 200, got 999.0$'):
        check_named(Demo(rate_hz=999.0))
    with pytest.raises(SettingsError, match=r'^demo\.rate_hz must be <= 200, got 999.0$'):
        check_named(Demo(rate_hz=999.0), 'demo')
    with pytest.raises(SettingsError, match=r'^demo\.count must not exceed --rate-hz$'):    # a relation
        check_named(Demo(rate_hz=2.0, count=3), 'demo')
    check_named(Demo(), 'demo')
