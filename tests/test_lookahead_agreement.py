"""scripts/results/lookahead_agreement.py: the emulated planners and the agreement's interval."""

import pytest
from script_loader import load_script

agreement = load_script("results/lookahead_agreement.py")


def _state(seed, level, full, fast, rewards, base="11"):
    return {"seed": seed, "level": level, "base": base, "full": full, "fast": fast,
            "rewards": rewards, "fast_cpu_s": 0.1, "full_cpu_s": 1.0, "fast_simulated": 10,
            "full_simulated": 80}


def test_emulation_sums_the_first_futures_over_the_horizon():
    # waiting fails in the first future only, at its 11th decision; fusing without optimising
    # costs as the rule does but for 18 points more at its 20th decision, in every future
    ok = [-1.0] * 20
    rewards = {"11": [ok] * 4, "10": [[-1.0] * 19 + [21.0 - 20.0 - 20.0]] * 4,
               "00": [[-1.0] * 10 + [-5000.0]] + [ok] * 3}
    state = _state(1, 0, "10", "10", rewards)
    # over 20 decisions both alternatives are worse than the rule: the rule; the cost counts the
    # failed rollout's 11 decisions
    assert agreement.emulate(state, 4, 20) == ("11", 80 + 80 + 11 + 60)
    # over 19 decisions the two are level: the rule
    assert agreement.emulate(state, 1, 19)[0] == "11"
    gain = {"11": [ok] * 4, "10": [[0.0] * 20] * 4, "00": [ok] * 4}
    assert agreement.emulate(_state(1, 0, "10", "10", gain), 1, 20) == ("10", 60)
    assert agreement.emulate(_state(1, 0, "10", "10", gain), 2, 5) == ("11", 30)


def test_agreement_is_pooled_and_averaged_over_worlds_with_an_interval():
    rewards = {"11": [[-1.0]] * 4, "10": [[-1.0]] * 4, "00": [[-1.0]] * 4}
    states = []
    for seed in range(8):
        for point in range(4):
            fast = "00" if (seed < 4 and point == 0) else "11"
            states.append(_state(seed, seed % 4, "11", fast, rewards))
    doc = agreement.agreement(states, [s["fast"] for s in states])
    assert doc["points"] == 32 and doc["worlds"] == 8
    assert doc["pooled"] == pytest.approx(28 / 32)
    mean, lo, hi = doc["mean_over_worlds"]
    assert mean == pytest.approx(0.875) and lo < mean < hi
    report = agreement.report(states)
    assert report["full_leaves_the_rule"] == 0 and report["fast_leaves_the_rule"] == 4
    assert report["cpu_ratio_pooled"] == pytest.approx(0.1)
    assert report["one_future_on_future_k"] == [1.0] * 4 and report["halves_agree"] == 1.0
