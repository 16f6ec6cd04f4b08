"""Metric names: one scheme the loops write and the plots, sweep summaries and tuner read, so
a schedule's own loops (a scope of their own) are plotted and pruned on like the shipped ones."""

from torchrl_stages.metric_names import STAGE, TASK, is_loop_evaluation, metric_name, parse_metric
from torchrl_stages.plots import read_stage_metrics
from torchrl_stages.schedules.joint import JOINT
from torchrl_stages.sweeps.figures import _read_curves
from torchrl_stages.tune import TrialPruning


def test_every_loop_scope_is_read_back_by_every_reader(tmp_path):
    names = [
        metric_name("eval", STAGE, 2, "success_rate"),
        metric_name("eval", JOINT, 1, "success_rate"),
        metric_name("eval", "phase", 0, "success_rate"),  # a schedule's own loop
    ]
    assert [parse_metric(n).index for n in names] == [2, 1, 0]
    assert all(map(is_loop_evaluation, names))
    assert not is_loop_evaluation(metric_name("eval", TASK, None, "success_rate"))
    csv = tmp_path / "metrics.csv"
    csv.write_text("name,step,value\n" + "".join(f"{n},64,0.5\n" for n in names))
    rows = read_stage_metrics(csv)
    assert ("eval", "phase", "success_rate") in rows[0]
    assert set(_read_curves(csv)) == {parse_metric(n) for n in names}  # the sweep's figures

    class Trial:
        reported: list = []

        def report(self, value, step):
            self.reported.append(step)

        def should_prune(self):
            return False

    trial = Trial()
    pruning = TrialPruning(trial)
    for name in names:
        pruning({name: 0.5}, 64)
    assert trial.reported == [0, 1, 2]
