"""A trained stacked policy, stage function included, as one ``torch.export`` ``.pt2`` file
that runs with PyTorch alone (``stages-export RUN_DIR FILE``)."""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torch import nn
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_stages.integrity import atomic_write
from torchrl_stages.policy import StackedPolicy
from torchrl_stages.runs.layout import RunDirError
from torchrl_stages.runs.loading import load_run, run_policy

#: the JSON file, inside the ``.pt2`` file, that names the program's inputs and outputs
METADATA = "policy.json"

#: entries of an env's TensorDicts that are no observation
_NOT_OBSERVED = {"done", "terminated", "truncated", "reward", "is_init", "success", "_reset"}


class TensorPolicy(nn.Module):
    """A stacked policy on plain tensors: ``in_keys``' tensors in, ``out_keys``' out. Every
    stage policy runs on the whole batch, so the traced program has no data-dependent branch.

    Examples:
        >>> from tensordict.nn import TensorDictModule
        >>> p0 = TensorDictModule(lambda o: o[..., 0] * 0 + 5, ["observation"], ["action"])
        >>> p1 = TensorDictModule(lambda o: o[..., 0] * 0 + 7, ["observation"], ["action"])
        >>> stacked = StackedPolicy([p0, p1], stage_fn=lambda td: td["observation"][..., :1] > 0)
        >>> TensorPolicy(stacked, ["observation"], ["action"])(torch.tensor([[-1.0], [1.0]]))
        (tensor([5., 7.]),)
    """

    def __init__(
        self, policy: StackedPolicy, in_keys: Sequence[NestedKey], out_keys: Sequence[NestedKey]
    ) -> None:
        super().__init__()
        self.policy = StackedPolicy(
            list(policy.policies),
            stage_fn=policy.stage_fn,
            stage_key=policy.stage_key,
            skip_absent=False,
        )
        self.in_keys, self.out_keys = list(in_keys), list(out_keys)

    def forward(self, *inputs: torch.Tensor) -> tuple[torch.Tensor, ...]:
        td = TensorDict(batch_size=inputs[0].shape[:1], device=inputs[0].device)
        for key, value in zip(self.in_keys, inputs, strict=True):
            td.set(key, value)
        out = self.policy(td)
        return tuple(out.get(key) for key in self.out_keys)


def _last(key: NestedKey) -> str:
    return key if isinstance(key, str) else key[-1]


def _describe(keys: Sequence[NestedKey], tensors: Sequence[torch.Tensor]) -> list[dict[str, Any]]:
    """Each key (a nested one: a JSON list) with its tensor's shape and dtype."""
    return [
        {"key": k, "shape": ["batch", *t.shape[1:]], "dtype": str(t.dtype).split(".")[-1]}
        for k, t in zip(keys, tensors, strict=True)
    ]


def input_keys(policy: StackedPolicy, example: TensorDictBase) -> list[NestedKey]:
    """The policies' inputs, and ``example``'s observations if the stage function needs more."""
    keys = list(policy.in_keys)
    if policy.stage_fn is None:
        return keys
    try:
        policy.stage_fn(example.select(*keys))
    except KeyError:
        others = example.exclude("next", policy.stage_key, *keys).keys(True, True)
        keys += [
            k for k in others if _last(k) not in _NOT_OBSERVED and "transition" not in _last(k)
        ]
    return keys


def export_policy(
    source: str | Path | StackedPolicy,
    path: str | Path,
    example: TensorDictBase | None = None,
    *,
    trust: bool = False,
) -> Path:
    """Exports the greedy policy of a run directory (or a :class:`StackedPolicy`) to ``path``;
    ``example``: an env TensorDict with one batch dimension of at least 2 (for a run: a reset of
    its task env by default)."""
    path = Path(path)
    if path.suffix != ".pt2":
        raise ValueError(f"{path}: the file must end in .pt2. Fix: name it e.g. policy.pt2")
    if not path.parent.is_dir():
        raise ValueError(f"{path.parent} is not a directory. Fix: create it, or pick another")
    if isinstance(source, StackedPolicy):
        if example is None:
            raise ValueError("exporting a policy needs example=, a TensorDict of the env's")
        policy = source
        out_keys = [k for k in policy.out_keys if _last(k) == "action"] or policy.out_keys
    else:
        run = load_run(source, trust=trust)
        policy = run_policy(run)
        actions = (run.task.specs(k).action_key for k in range(len(run.learners)))
        out_keys = list(dict.fromkeys(actions))
        if example is None:
            with contextlib.closing(run.task.base_env(2)) as env:
                example = env.reset()
    if example.batch_dims != 1 or example.batch_size[0] < 2:
        raise ValueError(
            f"example has batch size {list(example.batch_size)}. Fix: pass a TensorDict with "
            "one batch dimension of at least 2 (e.g. the reset of an env with batch_size=(2,))"
        )
    keys = input_keys(policy, example)
    inputs = tuple(example.get(k) for k in keys)
    module = TensorPolicy(policy, keys, out_keys).eval()
    batch = torch.export.Dim("batch", min=1)
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        outputs = module(*inputs)  # eager first: the stacked policy learns its output shapes
        program = torch.export.export(
            module, inputs, dynamic_shapes=(tuple({0: batch} for _ in inputs),)
        )
    meta = {
        "inputs": _describe(keys, inputs),
        "outputs": _describe(out_keys, outputs),
        "num_stages": len(policy.policies),
        "stage": "input" if policy.stage_fn is None else "stage function, in the program",
    }
    buffer = io.BytesIO()
    torch.export.save(program, buffer, extra_files={METADATA: json.dumps(meta)})
    atomic_write(path, lambda tmp: tmp.write_bytes(buffer.getvalue()))
    return path


def _names(entries: list[dict[str, Any]]) -> str:
    return ", ".join(
        f"{e['key'] if isinstance(e['key'], str) else '.'.join(e['key'])} "
        f"[{', '.join(map(str, e['shape']))}] {e['dtype']}"
        for e in entries
    )


def main(argv: list[str] | None = None) -> None:
    """``stages-export RUN_DIR FILE``: a finished run's greedy policy as a ``torch.export`` file."""
    parser = argparse.ArgumentParser(prog="stages-export", description=main.__doc__)
    parser.add_argument("run_dir", type=Path, help="a run directory written by stages-train")
    parser.add_argument("file", type=Path, help="the .pt2 file to write")
    parser.add_argument(
        "--trust",
        action="store_true",
        help="load a run whose config names code of its own (see stages-eval --trust)",
    )
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    try:
        file = export_policy(args.run_dir, args.file, trust=args.trust)
    except (RunDirError, ValueError) as err:
        print(f"stages-export: {err}", file=sys.stderr)
        sys.exit(2)
    extra = {METADATA: ""}
    torch.export.load(file, extra_files=extra)
    meta = json.loads(extra[METADATA])
    print(f"Wrote {file}: inputs {_names(meta['inputs'])}; outputs {_names(meta['outputs'])}")
