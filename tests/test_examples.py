"""The docstring examples that train a stage: skipped as doctests (training belongs in tests, not
in ``--doctest-modules``), run here as written, so that what they show stays true."""

from __future__ import annotations

import doctest
import inspect

import pytest

from torchrl_stages import stage
from torchrl_stages.schedules import backward, flat, joint

TRAINING_EXAMPLES = [
    backward.train_backward,
    backward.train_stage,
    flat.train_flat,
    joint.JointTrainer,
    stage.StageTrainer,
]


@pytest.mark.parametrize("obj", TRAINING_EXAMPLES, ids=lambda obj: obj.__qualname__)
def test_a_training_example_runs_as_written(obj):
    module = inspect.getmodule(obj)
    finder = doctest.DocTestFinder(recurse=False)
    (test,) = finder.find(obj, module=module, globs=dict(vars(module)))
    skipped = [example for example in test.examples if example.options.get(doctest.SKIP)]
    assert skipped, f"{obj.__qualname__}: no example is skipped as a doctest"
    for example in test.examples:
        example.options.pop(doctest.SKIP, None)  # run what --doctest-modules skips
    runner = doctest.DocTestRunner(verbose=False)
    result = runner.run(test)
    assert (result.failed, result.attempted) == (0, len(test.examples))
