"""An independent computation of evalstats' sequential comparison, from the formulas of
Waudby-Smith & Ramdas (2024), "Estimating means of bounded random variables by betting", JRSS-B:
the aGRAPA bet (their appendix B.2), the planned growth-optimal bet (scipy's bounded scalar
minimiser instead of evalstats' bisection), the confidence sequence's ends (scipy's brentq on the
crossing indicator's boundary) and Fisher's exact test (scipy.stats.fisher_exact).

Reads JSON cases on stdin, writes JSON answers on stdout."""
import json
import math
import sys

import numpy as np
from scipy.optimize import minimize_scalar
from scipy.stats import fisher_exact


def planned_stake(pa, effect, mu0, up, cap):
    pb = min(pa + effect, 1.0) if up else max(pa - effect, 0.0)
    q = np.array([pb * (1 - pa), 1 - pb * (1 - pa) - pa * (1 - pb), pa * (1 - pb)])
    x = np.array([1.0, 0.5, 0.0])
    g = (x - mu0) if up else (mu0 - x)
    if q @ g <= 0:
        return 0.0
    res = minimize_scalar(lambda lam: -(q @ np.log1p(lam * g)), bounds=(0.0, cap), method="bounded",
                          options={"xatol": 1e-12})
    return float(res.x)


def capital_path(z, a, m, up, plan):
    """ln K_t for t = 1..n of the process against m in direction up. Where the claim is that the
    difference lies on the side of m nearer 0, K is the average of two gamblers' capitals: the
    adaptive (or planned) one and one who bets as if the arms were equal (X's mean 1/2)."""
    mu0 = (m + 1) / 2
    room = 1 / mu0 if up else 1 / (1 - mu0)
    mixed = (up and m < 0) or ((not up) and m > 0)
    x = (np.asarray(z) + 1) / 2
    logs = [0.0, 0.0]
    out = []
    sum_x = sum_sq = sum_a = 0.0
    for t in range(len(x)):
        mean = (0.5 + sum_x) / (t + 1)
        var = (0.25 + sum_sq) / (t + 1)

        def towards(target):
            d = target - mu0
            lam = d / (var + d * d)
            return min(max(lam if up else -lam, 0.0), 0.5 * room)

        if plan is None:
            first = towards(mean)
        else:
            first = planned_stake((0.5 + sum_a) / (t + 1), plan, mu0, up, 0.9 * room)
        stakes = [first, towards(0.5) if mixed else 0.0]
        gain = (x[t] - mu0) if up else (mu0 - x[t])
        logs = [k + math.log1p(s * gain) for k, s in zip(logs, stakes)]
        out.append(float(np.logaddexp(logs[0], logs[1]) - math.log(2)) if mixed else logs[0])
        sum_x += x[t]
        sum_a += a[t]
        sum_sq += (x[t] - (0.5 + sum_x) / (t + 2)) ** 2
    return out


def crosses(z, a, m, up, plan, alpha):
    return max(capital_path(z, a, m, up, plan), default=-1.0) >= math.log(2 / alpha)


def cs_end(z, a, up, plan, alpha):
    centre = float(np.mean(z))
    far = -1.0 if up else 1.0
    if not crosses(z, a, far * (1 - 1e-9), up, plan, alpha):
        return far
    # The boundary between excluded (far side) and kept (centre side): bisection on the indicator
    # to 1e-10, written independently of evalstats' loop.
    lo, hi = sorted([far, centre])
    for _ in range(60):
        mid = (lo + hi) / 2
        excluded = crosses(z, a, mid, up, plan, alpha)
        if up:
            lo, hi = (mid, hi) if excluded else (lo, mid)
        else:
            lo, hi = (lo, mid) if excluded else (mid, hi)
    return lo if up else hi


def main():
    cases = json.load(sys.stdin)
    out = []
    for c in cases:
        if c["kind"] == "fisher":
            _, p = fisher_exact([[c["k1"], c["n1"] - c["k1"]], [c["k2"], c["n2"] - c["k2"]]])
            out.append({"p": float(p)})
            continue
        a, b = np.array(c["a"], float), np.array(c["b"], float)
        z = b - a
        d, alpha, plan = c["margin"], c["alpha"], c["plan"]
        logs = [capital_path(z, a, m, up, plan)[-1] for (m, up) in [(0, True), (-d, False), (-d, True), (d, False)]]
        out.append({
            "log_e": logs,
            "cs": [cs_end(z, a, True, plan, alpha), cs_end(z, a, False, plan, alpha)],
        })
    json.dump(out, sys.stdout)


if __name__ == "__main__":
    main()
