"""Names and paths are validated whole: a trailing newline (which a `$` anchor lets through) is refused."""
import os

import pytest

from assist_common.atomic import remove_stale_temporaries
from assist_common.mavlink_io import parse_endpoint


@pytest.mark.parametrize('url', ['/dev/ttyACM0\n', 'udpin:localhost\n:14550', 'tcp:vehicle.local\n:5760'])
def test_an_endpoint_with_a_trailing_newline_is_refused(url):
    with pytest.raises(ValueError, match='MAVLink endpoint|serial endpoint'):
        parse_endpoint(url)


def test_endpoints_without_the_newline_are_accepted():
    assert parse_endpoint('/dev/ttyACM0').device == '/dev/ttyACM0'
    assert parse_endpoint('udpin:localhost:14550').host == 'localhost'


def test_a_name_that_only_starts_like_a_temporary_is_not_removed(tmp_path):
    dead = 2 ** 22 + 12345                      # above Linux's largest pid: no such process
    odd = tmp_path / f'.replay.tmp{dead}\n'
    odd.write_text('not ours')
    stale = tmp_path / f'.replay.tmp{dead}'
    stale.write_text('ours')
    assert remove_stale_temporaries(tmp_path) == [stale]
    assert odd.exists() and os.listdir(tmp_path) == [odd.name]
