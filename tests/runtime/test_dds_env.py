"""Which DDS settings RORY's processes get: UDPv4 only, under every discovery range."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from rory_runtime.dds import fast_rediscovery_env, node_profile_env

NS = {'f': 'http://www.eprosima.com'}


@pytest.mark.parametrize('reach', ['SUBNET', 'SYSTEM_DEFAULT', ''])
def test_outside_localhost_the_builtin_transports_are_udpv4(reach: str) -> None:
    env = fast_rediscovery_env({'ROS_AUTOMATIC_DISCOVERY_RANGE': reach})
    assert env['FASTDDS_BUILTIN_TRANSPORTS'] == 'UDPv4'
    assert Path(env['FASTRTPS_DEFAULT_PROFILES_FILE']).name == 'fast_rediscovery.xml'
    assert 'ROS_AUTOMATIC_DISCOVERY_RANGE' not in env  # the operator's reach is kept


@pytest.mark.parametrize('reach', ['LOCALHOST', 'localhost'])
def test_localhost_is_made_with_a_udp_profile_on_the_loopback(reach: str) -> None:
    # Under LOCALHOST rmw_fastrtps brings shared memory back whatever the builtin transports
    # say; the same reach comes from SUBNET with UDPv4 bound to 127.0.0.1.
    env = fast_rediscovery_env({'ROS_AUTOMATIC_DISCOVERY_RANGE': reach})
    assert env['ROS_AUTOMATIC_DISCOVERY_RANGE'] == 'SUBNET'
    profile = ET.parse(env['FASTRTPS_DEFAULT_PROFILES_FILE']).getroot()
    transports = profile.findall('.//f:transport_descriptor', NS)
    assert [t.findtext('f:type', namespaces=NS) for t in transports] == ['UDPv4']
    assert [a.text for a in profile.findall('.//f:interfaceWhiteList/f:address', NS)] == [
        '127.0.0.1']
    assert profile.findtext('.//f:useBuiltinTransports', namespaces=NS) == 'false'
    assert [a.text for a in profile.findall('.//f:initialPeersList//f:address', NS)] == [
        '127.0.0.1']


def test_the_two_profiles_agree_on_discovery_and_heartbeat() -> None:
    # The localhost profile differs in transports only.
    def timing(path: str) -> list[str]:
        root = ET.parse(path).getroot()
        parts = [root.find('.//f:discovery_config', NS), root.find('.//f:publisher', NS)]
        return [ET.canonicalize(ET.tostring(e), strip_text=True) for e in parts if e is not None]

    plain = fast_rediscovery_env({})['FASTRTPS_DEFAULT_PROFILES_FILE']
    local = fast_rediscovery_env({'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST'})
    assert len(timing(plain)) == 2
    assert timing(plain) == timing(local['FASTRTPS_DEFAULT_PROFILES_FILE'])


@pytest.mark.parametrize('reach', ['LOCALHOST', 'SUBNET'])
def test_a_node_gets_the_node_variant_of_rorys_profile(reach: str) -> None:
    # The same settings, and its builtin writers asynchronous (a cold node hears the answers to
    # its first announcement) with readers that ask for what they missed at once.
    env = fast_rediscovery_env({'ROS_AUTOMATIC_DISCOVERY_RANGE': reach})
    node = node_profile_env(env)
    base = env['FASTRTPS_DEFAULT_PROFILES_FILE']
    assert node == {'FASTRTPS_DEFAULT_PROFILES_FILE': base.replace('.xml', '_node.xml')}
    plain, variant = ET.parse(base).getroot(), ET.parse(node[
        'FASTRTPS_DEFAULT_PROFILES_FILE']).getroot()
    for part in ('.//f:discovery_config', './/f:publisher', './/f:transport_descriptors'):
        mine, theirs = plain.find(part, NS), variant.find(part, NS)
        assert (mine is None) == (theirs is None)
        if mine is not None and theirs is not None:
            assert ET.canonicalize(ET.tostring(mine), strip_text=True) == ET.canonicalize(
                ET.tostring(theirs), strip_text=True)
    assert variant.findtext('.//f:throughputController/f:bytesPerPeriod', namespaces=NS) == '0'
    assert plain.find('.//f:throughputController', NS) is None
    assert variant.findtext('.//f:subscriber//f:initialAcknackDelay/f:nanosec',
                            namespaces=NS) == '2000000'


def test_an_operators_own_profile_is_left_to_the_node() -> None:
    assert node_profile_env({'FASTRTPS_DEFAULT_PROFILES_FILE': '/etc/robot/dds.xml'}) == {}
    assert node_profile_env({}) == {}
