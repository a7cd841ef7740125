"""`rory eval`'s command line: which methods also run at the other replay pace."""

from __future__ import annotations

import pytest

from rory_eval.evaluation.cli import main, parse_args


def test_rory_also_runs_paced_by_default_but_not_in_the_quick_evaluation() -> None:
    assert parse_args([]).other_pace == ['rory']
    assert parse_args(['--replay', 'paced']).other_pace == ['rory']  # then fast beside
    assert parse_args(['--quick']).other_pace == []
    assert parse_args(['--methods', 'restart', 'checkpoint']).other_pace == []
    assert parse_args(['--other-pace']).other_pace == []
    assert parse_args(['--other-pace', 'replay', 'rory']).other_pace == ['replay', 'rory']


def test_a_method_without_a_pace_is_refused_in_one_line(capsys: pytest.CaptureFixture[str]
                                                         ) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(['--other-pace', 'restart'])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert "--other-pace: invalid choice: 'restart'" in err[-1]
