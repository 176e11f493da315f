import json

from fwk.plugins import get_registry
from fwk.testing.task import TaskContract

Study = get_registry().get("task", "spectral-study")


class TestSpectralStudyContract(TaskContract):
    component = Study
    params = {"dataset": {"name": "synthetic-heads", "n_vertices": 800, "n_subjects": 4}, "ks": [10, 40, 120]}

    def test_errors_fall_with_k_and_claim_reported(self, tmp_path):
        ctx = self._run(tmp_path)
        m = json.loads((ctx.run_dir / "metrics.json").read_text())
        for curve in m["study"].values():
            assert curve["E_ave"] == sorted(curve["E_ave"], reverse=True)
            assert all(mx >= av for mx, av in zip(curve["E_max"], curve["E_ave"]))
        assert "holds" in m["claim"]
        assert "Claim" in (ctx.run_dir / "report.md").read_text()
