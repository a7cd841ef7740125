"""The six-target storm of ``make faults`` (rory_eval/faults/stack_storm.py) judged on made-up
runs: what passes, and each way it fails (a node not back, the safe state released early or
held late, the last node too slow, a target wrong); when the stack counts as settled; its
command line. No process is started."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from rory_eval.faults import stack_storm
from rory_eval.faults.stack_storm import STACK, analyse, describe, settled

KILL = 1000.0  # wall s
WARM = ('amcl', 'navigator', 'grid_slam')  # the pool of three, taken first
BACK = {'amcl': 0.060, 'navigator': 0.080, 'grid_slam': 0.095, 'graph_slam': 0.250,
        'depth_mapper': 0.300, 'lama_local': 0.420}  # s after the kill; lama_local last
STEPS = {'s1_ms': 0.4, 's2_ms': 1.0, 'restart_ms': 150.0, 'restore_ms': 30.0, 'sync_ms': 5.0,
         'replay_ms': 20.0, 's4_ms': 2.0}


def kills() -> list[tuple[float, str, int]]:
    return [(KILL + i * 1e-5, node, 100 + i) for i, node in enumerate(STACK)]


def events(back: dict[str, float] | None = None) -> list[dict[str, Any]]:
    """A storm's events.jsonl: the first starts, the kill, the hold, six recoveries, the
    release in the last one's S4."""
    back = BACK if back is None else back
    out: list[dict[str, Any]] = []
    for i, node in enumerate(STACK):
        out += [{'t': 900.0 + i, 'kind': 'spawn', 'node': node, 'incarnation': 1, 'warm': False},
                {'t': 901.0 + i, 'kind': 'state', 'node': node, 'new': 'RUNNING'}]
    out += [{'t': KILL + 0.001, 'kind': 'exit', 'node': node} for node in STACK]
    out.append({'t': KILL + 0.002, 'kind': 'safe_state', 'node': 'grid_slam', 'what': 'held',
                'topic': '/e_stop'})
    out += [{'t': KILL + 0.003, 'kind': 'spawn', 'node': node, 'incarnation': 2,
             'warm': node in WARM} for node in STACK]
    ordered = sorted(back, key=back.__getitem__)
    for node in ordered:
        if node == ordered[-1]:
            out.append({'t': KILL + back[node], 'kind': 'safe_state', 'node': node,
                        'what': 'released', 'topic': '/e_stop'})
        out.append({'t': KILL + back[node], 'kind': 'recovered', 'node': node, 'incarnation': 2,
                    'total_ms': back[node] * 1000 - 1.0, **STEPS})
    return out


def safe(last: float = 0.420) -> list[tuple[float, bool]]:
    return [(KILL + 0.004, True), (KILL + last + 0.001, False)]


def correct() -> dict[str, dict[str, Any]]:
    return {node: {'correct': True, 'measures': {}, 'reason': ''} for node in STACK}


def test_six_back_correct_the_stop_held_to_the_last_and_in_time_pass() -> None:
    storm = analyse(kills(), events(), safe(), correct())
    assert storm.problems == [] and storm.passed
    assert [(r.node, r.warm, r.back_ms) for r in storm.recoveries] == [
        ('amcl', True, 60.0), ('navigator', True, 80.0), ('grid_slam', True, 95.0),
        ('graph_slam', False, 250.0), ('depth_mapper', False, 300.0),
        ('lama_local', False, 420.0)]
    assert storm.recoveries[0].total_ms == 59.0 and storm.recoveries[0].steps == STEPS
    assert {r.exit_ms for r in storm.recoveries} == {1.0}
    assert storm.last_back_ms == 420.0
    assert storm.hold_after_ms == 4.0 and storm.release_after_ms == 1.0
    line = describe(storm)
    assert storm.kill_spread_ms == pytest.approx(0.05)
    assert line.startswith('PASS | last back 420 ms after the kill (six kills over 0.05 ms) '
                           '(bound 1000)')
    assert 'amcl 59w/60' in line and 'lama_local 419c/420' in line
    assert 'judges 6/6 correct' in line


def test_the_last_node_back_after_one_second_fails() -> None:
    late = {**BACK, 'lama_local': 1.2}
    storm = analyse(kills(), events(late), safe(1.2), correct())
    assert storm.problems == ['the last node back 1200.0 ms after the kill (bound 1000 ms)']


def test_a_node_not_back_fails_and_so_does_the_safe_state_it_holds() -> None:
    back = {n: s for n, s in BACK.items() if n != 'lama_local'}
    found = [e for e in events(back) if e['kind'] != 'safe_state' or e['what'] == 'held']
    gave_up = {'t': KILL + 2.0, 'kind': 'fatal', 'node': 'lama_local'}
    storm = analyse(kills(), [*found, gave_up], safe()[:1], correct())
    assert 'lama_local: 0 recoveries after the kill, not 1' in storm.problems
    assert 'gave up: lama_local' in storm.problems
    assert "safe state: events ['held'], not one held and one released" in storm.problems
    assert 'safe state: /e_stop heard [True], not [True, False]' in storm.problems


def test_a_release_before_the_last_node_is_back_fails() -> None:
    found = events()
    # Released with the first node back, and held again for the others.
    found.insert(found.index(next(e for e in found if e['kind'] == 'recovered')),
                 {'t': KILL + 0.06, 'kind': 'safe_state', 'node': 'amcl', 'what': 'released'})
    stop = [(KILL + 0.004, True), (KILL + 0.061, False), (KILL + 0.07, True),
            (KILL + 0.421, False)]
    storm = analyse(kills(), found, stop, correct())
    assert storm.safe_state == [
        "events ['held', 'released', 'released'], not one held and one released",
        '/e_stop heard [True, False, True, False], not [True, False]']
    assert not storm.passed


def test_a_release_heard_before_every_other_node_was_back_fails() -> None:
    storm = analyse(kills(), events(), [(KILL + 0.004, True), (KILL + 0.2, False)], correct())
    assert storm.safe_state == ['/e_stop released before every other node was back']


def test_a_node_back_before_the_hold_or_a_release_in_another_s4_fails() -> None:
    found = events()
    held = next(e for e in found if e.get('what') == 'held')
    found.remove(held)
    found.insert(found.index(next(e for e in found if e['kind'] == 'recovered')) + 1, held)
    assert analyse(kills(), found, safe(), correct()).safe_state == [
        'amcl was back before the safe state was held']
    found = events()
    released = next(e for e in found if e.get('what') == 'released')
    released['node'] = 'amcl'
    found.remove(released)
    found.insert(found.index(next(e for e in found if e['node'] == 'depth_mapper'
                                  and e['kind'] == 'recovered')) + 1, released)
    assert analyse(kills(), found, safe(), correct()).safe_state == [
        'released in the S4 of amcl, not of the last node back (lama_local)']


def test_a_stop_heard_before_the_kill_fails() -> None:
    storm = analyse(kills(), events(), [(KILL - 5.0, False), *safe()], correct())
    assert storm.safe_state == ['/e_stop carried [False] before the kill']


def test_a_wrong_or_unjudged_target_fails() -> None:
    verdicts = correct()
    verdicts['grid_slam'] = {'correct': False, 'reason': 'coverage 0.500 < 0.9'}
    verdicts['amcl'] = {'correct': None, 'reason': 'the reference run did not reach the goal'}
    del verdicts['navigator']
    storm = analyse(kills(), events(), safe(), verdicts)
    assert storm.problems == [
        'grid_slam: wrong (coverage 0.500 < 0.9)',
        'amcl: not judged (the reference run did not reach the goal)',
        'navigator: not judged']
    assert 'judges 3/6 correct' in describe(storm)


def test_kills_more_than_a_millisecond_apart_are_not_the_same_moment() -> None:
    spread = [(t + (0.0015 if node == 'navigator' else 0.0), node, pid)
              for t, node, pid in kills()]
    storm = analyse(spread, events(), safe(), correct())
    assert storm.problems == ['struck over 1.5 ms, not within one millisecond']


def test_a_strike_that_missed_a_node_fails() -> None:
    storm = analyse(kills()[:5], events(), safe(), correct())
    assert storm.problems[0].startswith("struck ['grid_slam', 'graph_slam', 'depth_mapper', "
                                        "'amcl', 'lama_local'], not each of")


def _write_events(store: Path, records: list[dict[str, Any]]) -> None:
    import json

    store.mkdir(exist_ok=True)
    (store / 'events.jsonl').write_text(''.join(json.dumps(r) + '\n' for r in records))


def test_the_stack_is_settled_once_running_checkpointed_and_the_pool_ready(
        tmp_path: Path) -> None:
    store, log = tmp_path / 'store', tmp_path / 'supervisor.log'
    up = [{'kind': 'state', 'node': n, 'new': 'RUNNING'} for n in STACK]
    _write_events(store, up)
    assert settled(store, log, 3) == '; '.join(
        [f'{n} has no checkpoint' for n in STACK] + ['0 of 3 standbys ready'])
    checkpoints = [{'kind': 'checkpoint', 'node': n} for n in STACK]
    standbys = [{'kind': 'standby', 'node': 'amcl', 'pid': pid} for pid in (11, 12, 13)]
    _write_events(store, up + checkpoints + standbys)
    log.write_text('[rory] standby pid 11 ready in 210 ms\n[rory] standby pid 12 ready in 250 ms'
                   '\n[rory] standby pid 99 ready in 250 ms\n')  # 99: not one of this pool's
    assert settled(store, log, 3) == '2 of 3 standbys ready'
    log.write_text(log.read_text() + '[rory] standby pid 13 ready in 260 ms\n')
    assert settled(store, log, 3) is None
    _write_events(store, [*up[:-1], {'kind': 'state', 'node': 'navigator', 'new': 'CRASHED'},
                          *checkpoints, *standbys])
    assert settled(store, log, 3) == 'navigator not running'


def test_each_mapping_target_has_its_own_map_topic_and_the_clock_waits_for_every_reader() -> None:
    argv = stack_storm.node_argv('graph_slam', 'real_room')
    assert argv[-2:] == ['-r', '/map:=/graph_slam/map']
    assert stack_storm.node_argv('amcl', 'real_room')[-1] != '/map:=/amcl/map'
    assert stack_storm.input_readers(ring=False) == {
        '/scan': 5, '/odom': 5, '/camera/depth/points': 1}
    assert stack_storm.input_readers(ring=True) == {
        '/scan': 6, '/odom': 6, '/camera/depth/points': 2}


@pytest.mark.parametrize(('argv', 'said'), [
    (['--runs', '0'], '--runs must be at least 1'),
    (['--runs', 'two'], "argument --runs: invalid int value: 'two'"),
    (['--world', 'moon'], 'argument --world: invalid choice'),
    (['--domain', '230'], '--domain must be 0-101'),
    (['--standbys', '0'], '--standbys must be at least 1'),
    (['--reference', 'none'], 'argument --reference: invalid choice'),
    (['--bound', '2'], 'unrecognized arguments: --bound 2'),
])
def test_bad_arguments_are_one_line_and_exit_2(argv: list[str], said: str,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_:
        stack_storm.main(argv)
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert err.count('\n') == 1 and said in err
    assert err.startswith('python -m rory_eval.faults.stack_storm: ')


def test_the_storms_stops_are_read_from_the_simulators_log(tmp_path: Path) -> None:
    log = tmp_path / 'sim.log'
    assert stack_storm.stops_of(log) == []
    log.write_text('real_room: running (seed 0)\n'
                   '[INFO] [1.5] [mujoco_sim]: e-stop ENGAGED at t=12.04\n'
                   '[INFO] [2.6] [mujoco_sim]: e-stop released at t=13.16\n'
                   '[INFO] [3.0] [mujoco_sim]: e-stop released at t=13.50\n'  # no stop to end
                   '[INFO] [4.0] [mujoco_sim]: e-stop ENGAGED at t=30.5\n')
    assert stack_storm.stops_of(log) == [(12.04, 13.16), (30.5, None)]


def test_the_model_on_the_geometry_is_shown_beside_the_judges(tmp_path: Path) -> None:
    import numpy as np

    # real_room: the floor is z = 0; a point 1 m above the floor in its open middle is on no
    # surface.
    model = tmp_path / 'final_model.npy'
    np.save(model, np.array([[1.0, 1.0, 0.0], [1.2, 1.0, 0.01], [1.5, 1.5, 0.02],
                             [1.5, 1.5, 1.0]]))
    assert stack_storm.model_on_geometry(model, 'real_room') == pytest.approx(0.75)
    assert stack_storm.model_on_geometry(tmp_path / 'none.npy', 'real_room') is None
    storm = analyse([], [], [], {})
    storm.model_on_geometry = {'storm': 0.9918, 'reference': 0.9924}
    assert ('depth_mapper model 99.18% of points within 5 cm of the geometry, reference '
            '99.24%') in describe(storm)
