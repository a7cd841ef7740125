"""``rory sim`` subcommands that need no ROS: list, info, map, route, render; ``rory sim`` runs
them as a child process."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from sim.cli import main
from sim.maps import load_map


def test_list_and_info(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(['list']) == 0
    out = capsys.readouterr().out
    assert 'office_small' in out and 'workshop' in out and 'real_room' in out
    assert main(['info', '--world', 'workshop']) == 0
    info = json.loads(capsys.readouterr().out)
    assert info['default_goal'] == 'behind_pillars'
    assert info['frames']['base_scan'] == [-0.064, 0.0, 0.18]
    assert info['lidar']['beams'] == 360 and info['depth']['width'] == 96
    assert info['depth']['height'] == 56 and info['depth']['hfov_deg'] == 87.0
    assert (info['depth']['range_min'], info['depth']['range_max']) == (0.2, 10.0)


def test_unknown_world_is_a_usage_error(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(['map', '--world', 'nowhere', '--out', 'x'])
    assert exc.value.code == 2
    assert "invalid choice: 'nowhere'" in capsys.readouterr().err


def test_map_writes_map_server_files(tmp_path: Path) -> None:
    assert main(['map', '--world', 'real_room', '--out', str(tmp_path)]) == 0
    grid = load_map(tmp_path / 'map.yaml')
    assert grid.resolution == 0.05
    assert (tmp_path / 'map.pgm').exists()


def test_route_then_render_the_recorded_path(tmp_path: Path,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / 'run'
    assert main(['route', '--world', 'real_room', '--seed', '4', '--out', str(out)]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary['completed'] and summary['collisions'] == 0
    assert json.loads((out / 'summary.json').read_text())['seed'] == 4
    header = (out / 'path.csv').read_text().splitlines()[0]
    assert header.startswith('t,x,y,yaw,odom_x,odom_y,odom_yaw')
    main(['map', '--world', 'real_room', '--out', str(tmp_path)])
    png = tmp_path / 'fig.png'
    assert main(['render', '--world', 'real_room', '--out', str(png), '--path',
                 str(out / 'path.csv'), '--odometry', '--map', str(tmp_path / 'map.yaml')]) == 0
    assert png.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'
    assert png.stat().st_size > 10_000


def test_render_names_a_bad_path_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / 'path.csv'
    bad.write_text('t,x\n0,1\n')
    code = main(['render', '--world', 'real_room', '--out', str(tmp_path / 'f.png'),
                 '--path', str(bad)])
    assert code == 2
    assert f"{bad}: column 'y' missing" in capsys.readouterr().err


def test_run_is_the_default_subcommand(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(['--world', 'nowhere', '--driver', 'route'])
    assert exc.value.code == 2
    assert 'rory sim run: error' in capsys.readouterr().err


def test_rory_sim_runs_the_simulator_cli_as_a_child(capfd: pytest.CaptureFixture[str]) -> None:
    from rory_runtime.cli import main as rory_main

    assert rory_main(['sim', 'info', '--world', 'real_room']) == 0
    assert json.loads(capfd.readouterr().out)['default_goal'] == 'far_corner'
    # Its exit code and its error, as the simulator's own parser gives them.
    assert rory_main(['sim', 'info', '--world', 'nowhere']) == 2
    assert "rory sim info: error: argument --world: invalid choice: 'nowhere'" in (
        capfd.readouterr().err)


def test_rory_sim_never_imports_the_simulator(tmp_path: Path) -> None:
    # Typed in a folder that holds a `sim` of its own: the child still runs the installed one.
    (tmp_path / 'sim').mkdir()
    (tmp_path / 'sim' / '__init__.py').write_text('')
    (tmp_path / 'sim' / '__main__.py').write_text('print("not the simulator")\n')
    env = {**os.environ, 'PYTHONPATH': str(Path(__file__).resolve().parents[2])}
    done = subprocess.run(
        [sys.executable, '-c', 'import sys\nfrom rory_runtime.cli import main\n'
         "code = main(['sim', 'list'])\n"
         "assert not [m for m in sys.modules if m == 'sim' or m.startswith('sim.')]\n"
         'sys.exit(code)'],
        capture_output=True, text=True, timeout=120, cwd=tmp_path, env=env)
    assert done.returncode == 0, done.stderr
    assert 'office_small' in done.stdout and 'not the simulator' not in done.stdout
