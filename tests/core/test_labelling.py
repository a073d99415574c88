"""Batched labelling in the core: label_frames and label_frames_isolated."""

import numpy as np
import pytest

from inkdiag_core import FaultClass, label_frames, label_frames_isolated, label_traces, load_model, simulate


def _frames(seed=0):
    r = simulate({FaultClass.HEALTHY_NOZZLE: 10, FaultClass.FULLY_BLOCKED: 5,
                  FaultClass.DEEPLY_DRIED: 5, FaultClass.EMPTY_CHANNEL_1: 4}, seed=seed)
    x = r.traces.astype(np.float32)
    x[3, 10] = np.nan  # an invalid row inside the second frame
    return [x[:3], x[3:11], x[11:12], x[12:]]


def test_label_frames_equals_each_frame_labelled_alone(fdi_model):
    model, manifest = load_model(fdi_model)
    frames = _frames()
    together = label_frames(model, frames, fd_threshold=0.3)
    assert [len(r.classes) for r in together] == [f.shape[0] for f in frames]
    for f, got in zip(frames, together):
        alone = label_traces(model, f, fd_threshold=0.3)
        assert list(got.classes) == list(alone.classes)
        np.testing.assert_allclose(got.confidence, alone.confidence, rtol=1e-12)
        assert list(got.valid) == list(alone.valid) and list(got.reasons) == list(alone.reasons)
    assert together[1].reasons[0] == "non_finite" and not together[1].valid[0]
    assert label_frames(model, []) == []


def test_label_frames_isolated_costs_a_bad_frame_only_itself(fdi_model):
    from inkdiag_core import label_frames_isolated

    model, _ = load_model(fdi_model)
    frames = _frames()
    good = label_frames_isolated(model, frames, fd_threshold=0.3, first_nozzles=[0, 3, 11, 12])
    assert [list(g.classes) for g in good] == [list(w.classes) for w in label_frames(model, frames, fd_threshold=0.3)]
    mixed = label_frames_isolated(model, [frames[1], np.zeros(512, np.float32)], fd_threshold=0.3,
                                  first_nozzles=[3, 11])
    assert list(mixed[0].classes) == list(good[1].classes)
    assert isinstance(mixed[1], str) and mixed[1].startswith("ValueError")


@pytest.mark.parametrize("max_abs_v, reason", [(10.0, "out_of_range"), (None, "non_finite_features")])
def test_an_extreme_row_costs_only_itself(fdi_model, max_abs_v, reason):
    """Rows with finite samples no sensor produces are invalid; every other row of the batch is labelled."""
    import warnings

    model, _ = load_model(fdi_model)
    frames = _frames()
    want = label_frames(model, frames, fd_threshold=0.3)
    bad = [np.array(f) for f in frames]
    big = np.finfo(np.float32).max
    bad[1][2, 100] = 1e30  # one spike
    bad[1][5, ::2], bad[1][5, 1::2] = big, -big  # alternating extremes
    bad[3][0, 7] = -big
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no numpy RuntimeWarning on this path
        got = label_frames(model, bad, fd_threshold=0.3, max_abs_v=max_abs_v)
        isolated = label_frames_isolated(model, bad, fd_threshold=0.3, first_nozzles=[0, 3, 11, 12],
                                         max_abs_v=max_abs_v)
    hit = {(1, 2), (1, 5), (3, 0)}
    for k, (g, w, iso) in enumerate(zip(got, want, isolated)):
        assert not isinstance(iso, str) and list(iso.classes) == list(g.classes)
        for i in range(len(g.classes)):
            if (k, i) in hit:
                assert (g.valid[i], g.reasons[i], g.classes[i]) == (False, reason, "")
                assert np.isnan(g.confidence[i])
            else:  # every other row as it was labelled without the extreme rows
                assert (g.valid[i], g.reasons[i], g.classes[i]) == (w.valid[i], w.reasons[i], w.classes[i])
                np.testing.assert_allclose(g.confidence[i], w.confidence[i], rtol=1e-12)
    assert got[1].reasons[0] == "non_finite"  # the NaN row keeps its reason


def test_label_frames_rejects_mixed_widths_and_bad_ndim(fdi_model):
    model, _ = load_model(fdi_model)
    a = np.zeros((2, 512), np.float32)
    with pytest.raises(ValueError, match="one sample count"):
        label_frames(model, [a, np.zeros((2, 256), np.float32)])
    with pytest.raises(ValueError, match="frame 1 has shape"):
        label_frames(model, [a, np.zeros(512, np.float32)])
