from fwk.plugins import get_registry
from fwk.testing.task import TaskContract


class TestReconstructContract(TaskContract):
    component = get_registry().get("task", "reconstruct")
    params = {"dataset": {"name": "synthetic-heads", "n_vertices": 300, "n_subjects": 12},
              "models": {"pca": {"name": "pca", "n_components": 4}}, "metrics": ["l1", "dame"], "renders": 1}
