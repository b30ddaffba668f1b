"""USER_DATA advertisement format and channel names."""
import pytest

from rclpy.qos import HistoryPolicy, QoSProfile

from rosidl_buffer_py import advertisement, channel
from rosidl_buffer_py.qos import history_metadata, parse_history_metadata

TYPEHASH = b'typehash=RIHS01_' + b'ab' * 32 + b';'


def rmw_parse_key_value(data: bytes) -> dict:
    """The rules of stock Jazzy's rmw::impl::cpp::parse_key_value (rmw/impl/cpp/key_value.hpp):
    alphanumeric keys, non-empty values, ';' ends a pair, a NUL where a key would start (after at
    least one pair) ends the string, anything else invalidates the WHOLE string ({})."""
    pairs, key, value, keyfound, prev = {}, b'', b'', False, 0
    if not data:
        return {}
    for u8 in data:
        if keyfound:
            if u8 == 0x3b and prev != 0x3b:
                prev = u8
                continue
            elif u8 != 0x3b and prev == 0x3b:
                if not value:
                    return {}
                pairs[key], key, value, keyfound = value, b'', b'', False
            else:
                value += bytes([u8])
        if not keyfound:
            if u8 == 0x3d:
                if not key:
                    return {}
                keyfound = True
            elif chr(u8).isalnum() and u8 < 128:
                key += bytes([u8])
            elif u8 == 0 and not key and pairs:
                break
            elif prev != 0x3b or key:
                return {}
        prev = u8
    if keyfound:
        if not value:
            return {}
        pairs[key] = value
    elif key:
        return {}
    return pairs


def test_round_trip_appended_to_rmw_typehash():
    data = advertisement.append(TYPEHASH, {'cpu': '', 'demo': 'b00t1d-f5'})
    assert data == TYPEHASH + b'\0BUFBE:cpu=;demo=b00t1d-f5;'
    assert advertisement.decode(data) == {'cpu': '', 'demo': 'b00t1d-f5'}


def test_stock_rmw_still_parses_the_typehash():
    data = advertisement.append(TYPEHASH, {'cpu': '', 'demo': 'meta.1.2'})
    assert rmw_parse_key_value(data) == {b'typehash': TYPEHASH[9:-1]}
    # without the separator, stock rmw would lose the typehash: the reason for it
    assert rmw_parse_key_value(TYPEHASH + b'BUFBE:cpu=;') == {}


def test_append_replaces_an_earlier_advertisement():
    once = advertisement.append(TYPEHASH, {'cpu': '', 'demo': 'x'})
    assert advertisement.append(once, {'cpu': ''}) == TYPEHASH + b'\0BUFBE:cpu=;'


def test_cpu_only_subscription_advertises_exactly_cpu():
    assert advertisement.encode({'cpu': ''}) == b'BUFBE:cpu=;'


def test_legacy_endpoint_has_no_advertisement():
    assert advertisement.decode(TYPEHASH) is None
    assert advertisement.decode(b'') is None


@pytest.mark.parametrize('garbage, expected', [
    (b'BUFBE:', {}),
    (b'BUFBE:;;;', {}),
    (b'BUFBE:cpu=;Bad Name=1;demo=m;', {'cpu': '', 'demo': 'm'}),
    (b'BUFBE:cpu;demo=a=b;', {'demo': 'a=b'}),
    (b'BUFBE:\xff\xfe=1;cpu=;', {'cpu': ''}),
])
def test_garbled_advertisements_keep_their_valid_entries(garbage, expected):
    assert advertisement.decode(TYPEHASH + garbage) == expected


@pytest.mark.parametrize('backends', [{'Demo': ''}, {'a;b': ''}, {'demo': 'x;y'},
                                      {'demo': 'caf\u00e9'}, {'demo': 'a\nb'}])
def test_invalid_names_and_metadata_are_refused(backends):
    with pytest.raises(advertisement.AdvertisementError):
        advertisement.encode(backends)


def test_channel_topic_uses_full_gids():
    pub = bytes(range(16))
    sub = bytes(range(16, 32))
    name = channel.channel_topic('/camera/image', pub, sub)
    assert name == ('rt/camera/image/_buf/000102030405060708090a0b0c0d0e0f_'
                    '101112131415161718191a1b1c1d1e1f')
    assert channel.is_channel_topic(name)
    assert not channel.is_channel_topic(channel.dds_topic('/camera/image'))
    # two endpoints of one participant differ only after the 8-byte prefix: names must differ
    assert channel.channel_topic('/t', pub, sub) != channel.channel_topic(
        '/t', pub, sub[:12] + b'\x00' * 4)


@pytest.mark.parametrize('topic, pub, sub', [
    ('camera', bytes(16), bytes(16)), ('/t', bytes(8), bytes(16)), ('/t', bytes(16), bytes(24))])
def test_bad_channel_arguments(topic, pub, sub):
    with pytest.raises(ValueError):
        channel.channel_topic(topic, pub, sub)


@pytest.mark.parametrize('qos, text, depth', [
    (QoSProfile(depth=50), 'keep_last.50', 50),
    (QoSProfile(depth=1), 'keep_last.1', 1),
    (QoSProfile(depth=10, history=HistoryPolicy.KEEP_ALL), 'keep_all', 0),
])
def test_a_subscriptions_history_round_trips_in_its_cpu_entry(qos, text, depth):
    assert history_metadata(qos) == text and parse_history_metadata(text) == depth
    assert advertisement.decode(advertisement.encode({'cpu': text})) == {'cpu': text}


@pytest.mark.parametrize('text', [None, '', 'keep_last.', 'keep_last.0', 'keep_last.-3',
                                  'keep_last.1e3', 'keep_last.' + '9' * 12, 'KEEP_ALL', 'x'])
def test_a_history_from_the_network_that_says_nothing_usable_is_unknown(text):
    assert parse_history_metadata(text) is None  # the publisher then treats it as KEEP_ALL
