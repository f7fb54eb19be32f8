"""bench graph: how frames are matched to their latent and command and which count as lost (no ROS)."""
import pytest

from bench.bench_graph import count_frames

S = 50_000_000          # one camera period (50 ms) in ns


def _frames(n, gap_s=0.05, valid=1.0, t0=10.0):
    return [(k * S, t0 + k * gap_s, valid) for k in range(n)]


def test_counting_starts_at_the_first_frame_with_both_a_pad_estimate_and_a_command():
    fr = _frames(12)
    cm = {s: t + 0.006 for s, t, _ in fr}                      # commands from the first frame on
    pad = {s: t + 0.004 for s, t, _ in fr[3:]}                 # pad estimates only from frame 3
    c = count_frames(fr, pad, cm, frames=8)
    assert len(c['gaps']) == 8
    assert c['lost'] == {'latent': 0, 'cmd': 0, 'no_depth': 0, 'burst': 0}
    assert c['to_latent'] == pytest.approx([0.004] * 8)
    assert c['to_cmd'] == pytest.approx([0.006] * 8)


def test_a_late_latent_a_missing_command_sparse_depth_and_a_burst_are_told_apart():
    fr = _frames(10)
    fr[4] = (4 * S, fr[4][1], 0.0)                             # depth with no valid pixels
    fr[7] = (7 * S, fr[8][1] - 0.001, 1.0)                     # frame 8 arrives 1 ms after frame 7
    pad = {s: t + 0.004 for s, t, _ in fr}
    cm = {s: t + 0.006 for s, t, _ in fr}
    pad[2 * S] = fr[3][1] + 0.001                              # frame 2's latent after frame 3 arrived
    del cm[5 * S]                                              # frame 5 never got a command
    del pad[4 * S], cm[4 * S], pad[7 * S], cm[7 * S]           # no outputs for the sparse and the burst frame
    c = count_frames(fr, pad, cm, frames=9)
    assert c['lost'] == {'latent': 1, 'cmd': 1, 'no_depth': 1, 'burst': 1}
    assert len(c['to_latent']) == 6 and len(c['to_cmd']) == 6    # of frames 0-8: not 2, 4, 7 / not 4, 5, 7
    assert sum(g < 0.025 for g in c['gaps']) == 1


def test_no_frame_with_both_outputs_is_an_error():
    fr = _frames(3)
    with pytest.raises(RuntimeError, match='no frame got both'):
        count_frames(fr, {}, {s: t for s, t, _ in fr})


def test_latent_receipts_are_matched_to_their_frame_else_the_pad_estimate_counts():
    fr = _frames(6)
    pad = {s: t + 0.004 for s, t, _ in fr}
    cm = {s: t + 0.006 for s, t, _ in fr}
    latents = [t + 0.003 for _, t, _ in fr]              # each latent 1 ms before its pad estimate
    del latents[2]                                        # frame 2's latent was not received: its pad time counts
    c = count_frames(fr, pad, cm, frames=5, latents=sorted(latents))
    assert c['to_latent'] == pytest.approx([0.003, 0.003, 0.004, 0.003, 0.003])
    # frame 1's pad estimate came late (after frame 2 arrived): frame 2's latent is the first one after it
    fr2 = _frames(4)
    pad2 = {s: t + 0.004 for s, t, _ in fr2}
    pad2[1 * S] = fr2[2][1] + 0.002
    lat2 = sorted([fr2[0][1] + 0.003, fr2[1][1] + 0.049, fr2[2][1] + 0.003, fr2[3][1] + 0.003])
    c2 = count_frames(fr2, pad2, {s: t + 0.006 for s, t, _ in fr2}, frames=3, latents=lat2)
    assert c2['lost']['latent'] == 1                      # frame 1: its latent came after frame 2
    assert c2['to_latent'] == pytest.approx([0.003, 0.003])
