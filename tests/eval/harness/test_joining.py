"""``joining``: a run's discovery settings only while this process creates its participant."""

from __future__ import annotations

import os

import pytest

from rory_eval.harness.scenario import joining, scenario_env


def test_settings_hold_inside_and_the_environment_is_restored_after(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setenv('ROS_DOMAIN_ID', '3')
    monkeypatch.delenv('FASTRTPS_DEFAULT_PROFILES_FILE', raising=False)
    expected = {k: v for k, v in scenario_env(17).items() if k.startswith(('FAST', 'ROS_'))}
    before = dict(os.environ)
    with joining(17):
        assert os.environ['ROS_DOMAIN_ID'] == '17'
        assert {k: os.environ[k] for k in expected} == expected
    assert dict(os.environ) == before


def test_restored_when_the_participant_fails(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv('ROS_DOMAIN_ID', '3')
    with pytest.raises(RuntimeError), joining(17):
        raise RuntimeError('no participant')
    assert os.environ['ROS_DOMAIN_ID'] == '3'
