"""The Host/Origin allow-list of the pilot station: which names a page may use to reach it."""
import socket

import pytest

from assist_station.access import HostPolicy, allowed_hosts, parse_host, parse_origin


def test_a_loopback_bind_allows_the_loopback_names_on_its_port_only():
    allowed = allowed_hosts('127.0.0.1', 8080)
    assert allowed == {('127.0.0.1', 8080), ('localhost', 8080), ('::1', 8080)}
    assert allowed_hosts('localhost', 8080) == allowed
    assert allowed_hosts('::1', 9000) == {('127.0.0.1', 9000), ('localhost', 9000), ('::1', 9000)}


def test_other_binds_and_extra_names():
    assert allowed_hosts('192.168.1.20', 8080) == {('192.168.1.20', 8080)}
    assert allowed_hosts('Station.Lan', 8080, ['other.lan:9000']) == {('station.lan', 8080), ('other.lan', 9000)}
    wildcard = allowed_hosts('0.0.0.0', 8080)
    assert {('127.0.0.1', 8080), ('localhost', 8080), (socket.gethostname().lower(), 8080)} <= wildcard
    with pytest.raises(ValueError, match='bad/name'):
        allowed_hosts('127.0.0.1', 8080, ['bad/name'])
    with pytest.raises(ValueError):
        allowed_hosts('127.0.0.1', 0)


@pytest.mark.parametrize('text, expected', [
    ('127.0.0.1:8080', ('127.0.0.1', 8080)), ('LocalHost.:8080', ('localhost', 8080)),
    ('[::1]:8080', ('::1', 8080)), ('[0:0:0:0:0:0:0:1]:8080', ('::1', 8080)), ('localhost', ('localhost', 80))])
def test_host_headers_are_parsed_to_canonical_pairs(text, expected):
    assert parse_host(text) == expected


@pytest.mark.parametrize('text', ['evil@127.0.0.1:8080', '127.0.0.1:8080/x', '127.0.0.1:99999', '[::1', '',
                                  'a b:80', '[zz::1]:80', 'x' * 400])
def test_malformed_host_headers_are_refused(text):
    with pytest.raises(ValueError):
        parse_host(text)


def test_origins_must_be_an_http_page_on_an_allowed_name():
    policy = HostPolicy(allowed_hosts('127.0.0.1', 8080))
    for ok in ('http://127.0.0.1:8080', 'http://localhost:8080', 'http://[::1]:8080', 'HTTP://LOCALHOST:8080'):
        assert policy.origin_ok(ok), ok
    for bad in ('null', 'http://rebind.example:8080', 'http://127.0.0.1:8081', 'http://127.0.0.1',
                'file://', 'chrome-extension://abc', 'http://127.0.0.1:8080/path', 'ws://127.0.0.1:8080'):
        assert not policy.origin_ok(bad), bad
    assert parse_origin('https://localhost') == ('localhost', 443)
    assert policy.host_ok('127.0.0.1:8080') and not policy.host_ok(None) and not policy.host_ok('rebind.example:8080')
    assert '[::1]:8080' in policy.describe()
