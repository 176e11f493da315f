"""TaskContract: a task runs from its recipe keys in a real run context and writes its results.

Subclass and set ``component`` (the task class) and ``params`` (small recipe keys)::

    class TestMyTask(TaskContract):
        component = MyTask
        params = {"dataset": {"name": "synthetic-heads", "n_vertices": 300, "n_subjects": 12}}
"""
from __future__ import annotations

import json

import pytest


class TaskContract:
    component: type = None
    params: dict = {}
    train: dict = {"epochs": 1, "batch_size": 8}
    expects = ("metrics.json", "report.md")

    def _run(self, tmp_path):
        from fwk.engine import TrainConfig
        from fwk.plugins import get_registry
        from fwk.recipes import validate_params
        from fwk.runs import make_test_context

        reg = get_registry()
        params = validate_params(self.component, dict(self.params), "", reg, label=f"task {self.component.name}")
        ctx = make_test_context(tmp_path, **self.train)
        ctx.train = TrainConfig(**self.train)
        self.component(**params).run(ctx)
        return ctx

    def test_has_name_and_summary(self):
        assert isinstance(self.component.name, str) and self.component.name
        assert (self.component.__doc__ or "").strip(), "the first docstring line is the `fwk list` summary"

    def test_runs_and_writes_results(self, tmp_path):
        ctx = self._run(tmp_path)
        for f in self.expects:
            assert (ctx.run_dir / f).exists(), f"{self.component.name} did not write {f}"
        if (ctx.run_dir / "metrics.json").exists():
            data = json.loads((ctx.run_dir / "metrics.json").read_text())
            nums = []

            def walk(x):
                if isinstance(x, dict):
                    for v in x.values():
                        walk(v)
                elif isinstance(x, list):
                    for v in x:
                        walk(v)
                elif isinstance(x, (int, float)) and not isinstance(x, bool):
                    nums.append(float(x))

            walk(data)
            assert nums, "metrics.json holds no numbers"

    def test_rejects_unknown_key(self):
        from fwk.errors import RecipeError
        from fwk.plugins import get_registry
        from fwk.recipes import validate_params

        with pytest.raises(RecipeError, match="unknown parameter"):
            validate_params(self.component, {**self.params, "no_such_key_xyz": 1}, "", get_registry())
