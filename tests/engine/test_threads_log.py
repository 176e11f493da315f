"""log.txt says each thread count once per run: a count that flips as other fwk processes come
and go is not repeated at every epoch (issue 30)."""


def test_report_threads_says_each_count_once_per_log():
    from fwk.engine.threads import report_threads

    said, other = [], []
    for n in (1, 2, 1, 2, 1, 2):
        report_threads(said.append, n, f"{3 - n} fwk processes on 2 cores")
    assert said == ["threads: 1 (2 fwk processes on 2 cores)", "threads: 2 (1 fwk processes on 2 cores)"]
    assert report_threads(other.append, 1, "x") and other == ["threads: 1 (x)"]  # another run's log says it again


def test_thread_share_does_not_repeat_a_flipping_count(monkeypatch):
    import torch

    from fwk.engine import ThreadShare, callbacks

    counts = iter([1, 2, 1, 2, 1])
    before = torch.get_num_threads()

    def fake():
        n = next(counts)
        return n, f"{3 - n} fwk processes on 2 cores", True

    monkeypatch.setattr(callbacks, "apply_threads", fake)
    said = []
    share = ThreadShare(said.append)
    for _ in range(5):
        share.on_train_epoch_start(None, None)
    assert said == ["threads: 1 (2 fwk processes on 2 cores)", "threads: 2 (1 fwk processes on 2 cores)"]
    assert torch.get_num_threads() == before


def test_one_line_per_log_file_across_a_runs_contexts(tmp_path):
    """A run's scoped and child contexts (one per model, an inline sub-run) share its log.txt:
    fit says the count there once, not once per model."""
    from fwk.engine.threads import report_threads
    from fwk.runs import make_test_context

    ctx = make_test_context(tmp_path)
    for c in (ctx, ctx.scoped("a"), ctx.scoped("b"), ctx.child("sub")):
        report_threads(c.log, 2, "1 fwk process on 2 cores", c.log_file)
    assert ctx.log_file.read_text().count("threads: 2") == 1
