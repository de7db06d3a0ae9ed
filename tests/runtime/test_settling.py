"""thermod.runtime.settling: warming up until two consecutive windows agree on their p95 latency."""

from thermod.runtime import settling as S


def _feed(s, t0, t1, latency, fps=50.0):
    t = t0
    while t < t1:
        s.add(t, latency(t))
        t += 1.0 / fps


def test_a_slow_start_warms_up_then_settles_for_good():
    s = S.Settling(100.0)
    assert s.state(100.0) == {"warming_up": True, "steady_after_s": None}
    # 12 s of cold start (latency falling from 150 to 40 ms), then steady 40 ms
    _feed(s, 100.0, 112.0, lambda t: 0.150 - (t - 100.0) / 12.0 * 0.110)
    assert s.state(112.0)["warming_up"]
    _feed(s, 112.0, 130.0, lambda t: 0.040)
    st = s.state(130.0)
    assert not st["warming_up"] and st["steady_after_s"] == 25.0   # windows [115, 120) and [120, 125)
    _feed(s, 130.0, 135.0, lambda t: 0.500)                       # later trouble is not a cold start
    assert s.state(135.0)["steady_after_s"] == 25.0


def test_too_few_frames_in_a_window_do_not_count_as_steady():
    s = S.Settling(0.0)
    _feed(s, 0.0, 30.0, lambda t: 0.040, fps=2.0)                 # 10 frames per 5 s window
    assert s.state(30.0) == {"warming_up": True, "steady_after_s": None}
    # never settled: after GIVE_UP_S it is no longer called warming up, and not steady either
    assert s.state(S.GIVE_UP_S + 1.0) == {"warming_up": False, "steady_after_s": None}


def test_a_latency_that_keeps_moving_is_not_steady():
    s = S.Settling(0.0)
    _feed(s, 0.0, 40.0, lambda t: 0.040 * (1.5 if int(t / S.WINDOW_S) % 2 else 1.0))
    assert s.state(40.0)["steady_after_s"] is None
