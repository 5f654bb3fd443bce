#!/usr/bin/env python3
"""Independent simulator of AFM indentation recordings (recording/1 format).

Usage:  python3 sim.py OUTDIR        (writes OUTDIR/recs/recNN.{csv,toml} and OUTDIR/truth.json)

Chain (all in nm, nN, s):
  command x_cmd(t) -> [Bouc-Wen hysteresis] -> [log creep] -> piezo linear dynamics (2nd order)
  -> [instrument mode] -> base position z_b ; delta = z_b - z_surface [+ thermal drift]
  -> quasi-static cantilever k*d = F_rep + F_ext  (F_ext = drag - adhesion)
  -> viscoelastic contact (generalised Lee-Radok, Prony creep compliance, Tustin-exact recursion):
        g(h(t)) = (1 - nu^2) * integral J(t - s) dF_rep(s),   g = sphere (4/3)sqrt(R) h^1.5 / cone (2/pi) tan(a) h^2
  -> optical lever d/C_t + offset -> [detector nonlinearity] -> [channel delay] -> [mains]
  -> sampled at fs (every OS-th internal sample) -> white (+1/f) noise -> 18-bit quantisation.
Physics is integrated at OS = 8 x the recorded rate.
"""
import json
import math
import os
import sys

import numpy as np
from scipy import signal
from scipy.interpolate import CubicSpline

SEED = 2718281
OS = 8  # internal oversampling factor

EFFECTS = ["piezo_hysteresis", "piezo_creep", "thermal_drift", "missing_relaxation",
           "instrument_resonance", "adhesion", "tip_geometry", "hydrodynamic_drag",
           "channel_delay", "mains_interference", "detector_nonlinearity", "substrate_effect"]
POST_EFFECTS = {"channel_delay", "mains_interference", "detector_nonlinearity"}
ADC_LSB = 20.0 / 2 ** 18  # volts


def logu(rng, lo, hi):
    return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))


# ----------------------------------------------------------------------------- contact laws
def contact_prefactor(cfg):
    """g(h) = c * h^m for the *declared* tip (nm^2 when h in nm)."""
    if cfg["tip"]["shape"] == "sphere":
        return (4.0 / 3.0) * math.sqrt(cfg["tip"]["radius_nm"]), 1.5
    a = math.radians(cfg["tip"]["half_angle_deg"])
    return (2.0 / math.pi) * math.tan(a), 2.0


def sneddon_table(fprime, a_max, n_a=4000, n_q=1500):
    """Sneddon for an axisymmetric profile with slope f'(r): returns (h(a), G(a)=P/E*(a))."""
    th = (np.arange(n_q) + 0.5) * (np.pi / 2) / n_q  # midpoint rule
    dth = (np.pi / 2) / n_q
    a = np.linspace(0, a_max, n_a)[1:]
    s = np.sin(th)
    H = np.empty_like(a)
    G = np.empty_like(a)
    for i in range(0, len(a), 500):
        aa = a[i:i + 500, None]
        fp = fprime(aa * s[None, :])
        H[i:i + 500] = aa[:, 0] * fp.sum(1) * dth
        G[i:i + 500] = 2 * aa[:, 0] ** 2 * (s[None, :] ** 2 * fp).sum(1) * dth
    return np.concatenate([[0.0], H]), np.concatenate([[0.0], G])


def build_contact_law(cfg, eff, h_max):
    """Return ('pow', c, m) for the plain declared law, or ('tab', hgrid_step, gtab) otherwise."""
    c, m = contact_prefactor(cfg)
    tg = eff.get("tip_geometry")
    sub = eff.get("substrate_effect")
    if tg is None and sub is None:
        return ("pow", c, m)
    hgrid = np.linspace(0.0, h_max, 200001)
    if tg is None:
        g = c * hgrid ** m
    elif tg["kind"] == "power_law":
        # profile f(r) = r^2/(2R) * (r/a_ref)^eps  (n = 2+eps); exact Sneddon power-law solution
        R = cfg["tip"]["radius_nm"]
        n = 2.0 + tg["eps"]
        B = tg["a_ref_nm"] ** (-tg["eps"]) / (2 * R)

        def fprime(r):
            return n * B * np.power(r, n - 1)
        a_max = 1.0
        while True:
            Hh, _ = sneddon_table(fprime, a_max, n_a=50)
            if Hh[-1] > h_max:
                break
            a_max *= 2
        Hh, Gg = sneddon_table(fprime, a_max)
        g = np.interp(hgrid, Hh, Gg)
    elif tg["kind"] == "blunted_cone":
        al = math.radians(cfg["tip"]["half_angle_deg"])
        Rb = tg["R_b_nm"]
        b = Rb * math.cos(al)
        cot = 1.0 / math.tan(al)

        def fprime(r):
            rr = np.minimum(r, b)
            return np.where(r < b, rr / np.sqrt(np.maximum(Rb ** 2 - rr ** 2, 1e-30)), cot)
        a_max = 2.0 * h_max * math.tan(al) / math.pi + 2 * b + 10
        Hh, Gg = sneddon_table(fprime, a_max)
        g = np.interp(hgrid, Hh, Gg)
    else:
        raise ValueError(tg["kind"])
    if sub is not None:
        Ht = 1.0 / sub["inv_thickness_per_nm"]
        if cfg["tip"]["shape"] == "sphere":  # Dimitriadis et al. 2002, bonded, nu ~ 0.5
            x = np.sqrt(cfg["tip"]["radius_nm"] * hgrid) / Ht
            corr = 1 + 1.133 * x + 1.283 * x ** 2 + 0.769 * x ** 3 + 0.0975 * x ** 4
        else:  # Gavara & Chadwick 2012, bonded cone
            x = hgrid * math.tan(math.radians(cfg["tip"]["half_angle_deg"])) / Ht
            corr = 1 + 0.721 * x + 0.650 * x ** 2 + 0.491 * x ** 3 + 0.225 * x ** 4
        g = g * corr
    return ("tab", hgrid[1] - hgrid[0], g)


# ----------------------------------------------------------------------------- stage 1
def tf_filter(b, a, x, fs_int, prewarp_hz=None):
    if prewarp_hz is None:
        bd, ad = signal.bilinear(b, a, fs=fs_int)
    else:
        # prewarped Tustin: substitute s -> w0/tan(w0 T/2) * (z-1)/(z+1)
        w0 = 2 * math.pi * prewarp_hz
        K = w0 / math.tan(w0 / (2 * fs_int))
        bd, ad = signal.bilinear(b, a, fs=K / 2.0)
    zi = signal.lfilter_zi(bd, ad) * x[0]
    y, _ = signal.lfilter(bd, ad, x, zi=zi)
    return y


def second_order(x, f0, zeta, fs_int):
    """w^2/(s^2+2 zeta w s+w^2), discretised with first-order hold (exact for piecewise-linear input)."""
    w = 2 * math.pi * f0
    bd, ad, _ = signal.cont2discrete(([w * w], [1.0, 2 * zeta * w, w * w]), 1.0 / fs_int, method="foh")
    bd = np.ravel(bd)
    zi = signal.lfilter_zi(bd, ad) * x[0]
    y, _ = signal.lfilter(bd, ad, x, zi=zi)
    return y


def bouc_wen(x, p):
    """y = x - hbw,  dhbw = alpha*dx - beta*|dx|*hbw - gamma*dx*|hbw|  (Bouc-Wen, n = 1)."""
    al, be, ga = p["alpha"], p["beta_per_nm"], p["gamma_per_nm"]
    dx = np.diff(x, prepend=x[0])
    hb = np.empty_like(x)
    h = 0.0
    for i, d in enumerate(dx.tolist()):
        h += al * d - be * abs(d) * h - ga * d * abs(h)
        hb[i] = h
    return x - hb


def log_creep(x, p, fs_int):
    """Step response 1 - (gamma/2) * sum_j exp(-t/tau_j), tau_j 2 per decade 1 ms..100 s
    (~ gamma per decade of logarithmic creep; static gain = nominal)."""
    taus = 10.0 ** np.arange(-3.0, 2.01, 0.5)
    out = x.copy()
    for tau in taus:
        c = 1.0 / (2 * tau * fs_int)
        bd = np.array([c, c]) / (1 + c)
        ad = np.array([1.0, (c - 1) / (1 + c)])
        lp, _ = signal.lfilter(bd, ad, x, zi=signal.lfilter_zi(bd, ad) * x[0])
        out -= 0.5 * p["gamma"] * (x - lp)
    return out


def stage1(cfg, eff):
    """Actuator and mount: returns base position relative to the surface (delta), height sensor."""
    fsi = cfg["fs"] * OS
    x = cfg["_xcmd"].copy()
    if "piezo_hysteresis" in eff:
        x = bouc_wen(x, eff["piezo_hysteresis"])
    if "piezo_creep" in eff:
        x = log_creep(x, eff["piezo_creep"], fsi)
    x = second_order(x, cfg["piezo"]["f_n_hz"], cfg["piezo"]["zeta"], fsi)
    sensor = x.copy()
    if "instrument_resonance" in eff:
        p = eff["instrument_resonance"]
        m = second_order(x, p["f_r_hz"], 1.0 / (2 * p["Q"]), fsi)
        x = x + p["kappa"] * (m - x)
        if p.get("acoustic_frac", 0) > 0:
            ex = second_order(cfg["_acoustic_white"], p["f_r_hz"], 1.0 / (2 * p["Q"]), fsi)
            x = x + p["kappa"] * p["acoustic_frac"] * ex
    delta = x.copy()
    if "thermal_drift" in eff:
        delta = delta + eff["thermal_drift"]["amp_nm"] * cfg["_drift_unit"]
    return delta, x, sensor


# ----------------------------------------------------------------------------- stage 2
def stage2(cfg, eff, delta):
    """Quasi-static cantilever on a viscoelastic half-space; returns deflection (nm), contact flag."""
    fsi = cfg["fs"] * OS
    T = 1.0 / fsi
    k = cfg["k_nN_per_nm"]
    Jp = list(cfg["prony_J_nm2_per_nN"])  # (1-nu^2)*J in nm^2/nN, terms beyond glassy
    taus = list(cfg["prony_tau_s"])
    if "missing_relaxation" in eff:
        p = eff["missing_relaxation"]
        Jp.append(p["J4_frac"] * cfg["J_relaxed_nm2_per_nN"])
        taus.append(p["tau4_s"])
    Jg = cfg["J_glassy_nm2_per_nN"]
    cs = [T / (2 * t) for t in taus]
    aa = [(1 - c) / (1 + c) for c in cs]
    bb = [c / (1 + c) for c in cs]
    A = Jg + sum(j * b for j, b in zip(Jp, bb))
    nterm = len(Jp)
    xs = [0.0] * nterm
    hmax = float(np.max(delta)) * 1.5 + 50.0
    law = build_contact_law(cfg, eff, hmax)
    if law[0] == "pow":
        cpow, mpow = law[1], law[2]
        tab = None
    else:
        dh, gt = law[1], law[2]
        tab = gt.tolist()
        ntab = len(tab) - 1

        def gfun(h):
            u = h / dh
            i = int(u)
            if i >= ntab:
                i = ntab - 1
            s = tab[i + 1] - tab[i]
            return tab[i] + s * (u - i), s / dh
    # external force on the lever
    Fad = eff["adhesion"]["F_ad_nN"] if "adhesion" in eff else 0.0
    drag = eff.get("hydrodynamic_drag")
    if drag is not None:
        zdot = np.gradient(cfg["_zb_for_drag"], T)  # nm/s of the lever base
        zdot_l = zdot.tolist()
        beta0 = drag["beta0_nN_s_per_nm"]
        heff = drag["h_eff_nm"]
    N = len(delta)
    d_out = np.empty(N)
    cont = np.zeros(N, dtype=bool)
    Fprev = 0.0
    hprev = 0.0
    incont = False
    gap = 1e3
    dl = delta.tolist()
    for n in range(N):
        dn = dl[n]
        Fdrag = beta0 * heff / (gap + heff) * zdot_l[n] if drag is not None else 0.0
        B = 0.0
        for i in range(nterm):
            B += Jp[i] * (aa[i] * xs[i] + bb[i] * Fprev)
        Fe = Fdrag - Fad if incont else Fdrag
        h0 = dn - Fe / k
        contact = False
        if h0 > 0:
            g0 = cpow * h0 ** mpow if tab is None else gfun(h0)[0]
            if g0 > B:
                contact = True
            elif incont and Fad > 0:
                pass
        if not contact and incont and Fad > 0:
            # detached: re-evaluate without adhesion (snap-off)
            Fe = Fdrag
            h0 = dn - Fe / k
            if h0 > 0:
                g0 = cpow * h0 ** mpow if tab is None else gfun(h0)[0]
                contact = g0 > B
        if contact:
            if not incont and Fad > 0:
                # just touched: adhesion switches on (jump-to-contact)
                Fe = Fdrag - Fad
                h0 = dn - Fe / k
            Ak = A * k
            h = hprev if 0 < hprev < h0 else h0
            for it in range(60):
                if tab is None:
                    gh = cpow * h ** mpow
                    gp = mpow * gh / h if h > 0 else 0.0
                else:
                    gh, gp = gfun(h)
                psi = gh - Ak * (h0 - h) - B
                hn = h - psi / (gp + Ak)
                if hn > h0:
                    hn = h0
                if hn <= 0:
                    hn = 0.5 * h
                if abs(hn - h) < 1e-10 * (1.0 + h0):
                    h = hn
                    break
                h = hn
            F = k * (h0 - h)
            if F < 0:
                F = 0.0
            d = (F + Fe) / k
            gap = 0.0
            hprev = h
        else:
            F = 0.0
            d = Fdrag / k
            gap = max(-(dn - d), 0.0)
            hprev = 0.0
        for i in range(nterm):
            xs[i] = aa[i] * xs[i] + bb[i] * (F + Fprev)
        Fprev = F
        incont = contact
        d_out[n] = d
        cont[n] = contact
    return d_out, cont


# ----------------------------------------------------------------------------- stage 3
def detector(v, p):
    if p["form"] == "quadratic":
        return v + p["coef"] * v * v
    if p["form"] == "cubic":
        return v - p["coef"] * v ** 3
    if p["form"] == "tanh":  # saturating photodiode: Vs*tanh(v/Vs), coef = 1/Vs
        c = p["coef"]
        return np.tanh(c * v) / c
    raise ValueError(p["form"])


def mains(t, p, phase_shift=0.0):
    out = np.zeros_like(t)
    for j, (rel, ph) in enumerate(zip(p["harm_rel"], p["harm_phase"])):
        out += p["amp_v"] * rel * np.sin(2 * np.pi * (j + 1) * p["f_hz"] * t + ph + (j + 1) * phase_shift)
    return out


def stage3(cfg, eff, d_nm, ti):
    v = d_nm / cfg["Ct"] + cfg["offset_v"]
    if "detector_nonlinearity" in eff:
        v = detector(v, eff["detector_nonlinearity"])
    if "channel_delay" in eff:
        D = eff["channel_delay"]["delay_samples"] / cfg["fs"]
        cs = CubicSpline(ti, v)
        tq = ti - D
        v = np.where(tq >= ti[0], cs(np.clip(tq, ti[0], None)), v[0])
    if "mains_interference" in eff:
        v = v + mains(ti, eff["mains_interference"])
    return v[::OS]


def simulate_clean(cfg, eff, cache=None):
    """Clean recorded deflection (V) and contact mask for an effect dict; caches stage 1-2."""
    phys = {k: v for k, v in eff.items() if k not in POST_EFFECTS}
    key = json.dumps(phys, sort_keys=True, default=float)
    if cache is not None and key in cache:
        d, cont, zb, sensor = cache[key]
    else:
        delta, zb, sensor = stage1(cfg, phys)
        cfg["_zb_for_drag"] = zb
        d, cont = stage2(cfg, phys, delta)
        if cache is not None:
            cache[key] = (d, cont, zb, sensor)
    v = stage3(cfg, eff, d, cfg["_ti"])
    return v, cont[::OS], d, zb, sensor


# ----------------------------------------------------------------------------- nominal set-up
LINE_CANDIDATES = [1, 2, 3, 5, 7, 10, 15, 20, 30, 45, 60, 80, 100, 150, 200, 300, 450, 600, 800, 1000, 1300]


def gen_nominal(rng, hints):
    cfg = {}
    for _ in range(1000):
        fs = float(rng.choice([5000, 6250, 8000, 10000, 12500, 16000, 20000]))
        T = float(rng.choice([1.0, 1.5, 2.0, 2.5, 3.0, 4.0]))
        N = int(min(round(T * fs), 20000))
        if N / fs >= 0.9:
            break
    cfg["fs"], cfg["N"] = fs, N
    T = N / fs
    cfg["drive_kind"] = "v" if rng.random() < 0.7 else "nm"
    cfg["k"] = round(logu(rng, 0.02, 0.5), 6)  # N/m == nN/nm (declared == true)
    cfg["k_nN_per_nm"] = cfg["k"]
    cfg["Ct"] = round(float(rng.uniform(30, 120)), 4)
    shape = hints.get("shape") or ("sphere" if rng.random() < 0.6 else "cone")
    cfg["nu"] = 0.5 if rng.random() < 0.8 else round(float(rng.uniform(0.40, 0.49)), 3)
    cfg["protocol"] = hints.get("protocol") or ("multisine" if rng.random() < 0.6 else "step")
    for _ in range(5000):
        if shape == "sphere":
            R = round(logu(rng, 20, 5000), 3)
            cfg["tip"] = {"shape": "sphere", "radius_nm": R}
            h0 = float(np.clip(rng.uniform(0.05, 0.22) * R, 3, 600))
        else:
            cfg["tip"] = {"shape": "cone", "half_angle_deg": round(float(rng.uniform(15, 35)), 3)}
            h0 = logu(rng, 30, 500)
        d0 = logu(rng, *hints.get("d0_range", (8, 120)))
        if d0 / cfg["Ct"] > 6.0:
            continue
        F0 = cfg["k"] * d0
        c, m = contact_prefactor(cfg)
        Jrel = c * h0 ** m / F0  # nm^2/nN  == (1-nu^2) J * 1e9
        E_rel = (1 - cfg["nu"] ** 2) * 1e9 / Jrel
        if 1e3 <= E_rel <= 1e7 and (E_rel * 3 < 1e7 or True):
            break
    cfg["h0_nm"], cfg["d0_nm"], cfg["F0_nN"] = h0, d0, F0
    gfrac = float(rng.uniform(*hints.get("glassy_frac", (0.3, 0.7))))
    w = rng.dirichlet([2, 2, 2])
    taus = [logu(rng, 0.05, 0.4), logu(rng, 0.004, 0.025), logu(rng, 0.0003, 0.002)]
    if "tau1" in hints:
        taus[0] = logu(rng, *hints["tau1"])
    if "tau3" in hints:
        taus[2] = logu(rng, *hints["tau3"])
    cfg["J_relaxed_nm2_per_nN"] = Jrel
    cfg["J_glassy_nm2_per_nN"] = gfrac * Jrel
    cfg["prony_J_nm2_per_nN"] = [float(x) for x in (1 - gfrac) * Jrel * w]
    cfg["prony_tau_s"] = taus
    cfg["E_relaxed_Pa"] = E_rel
    cfg["E_instant_Pa"] = E_rel / gfrac
    # noise
    cfg["sigma_nm"] = logu(rng, 0.04, 0.3)
    cfg["sigma_v"] = cfg["sigma_nm"] / cfg["Ct"]
    cfg["pink_rel"] = float(rng.uniform(0.5, 1.5)) if (hints.get("pink") or rng.random() < 0.2) else 0.0
    if hints.get("no_pink"):
        cfg["pink_rel"] = 0.0
    cfg["offset_v"] = float(rng.uniform(-0.05, 0.05))
    # piezo
    if cfg["drive_kind"] == "v":
        cfg["piezo"] = {"gain_nm_per_v": round(logu(rng, 15, 150), 5), "f_n_hz": float(rng.uniform(1500, 6000)),
                        "zeta": float(rng.uniform(0.45, 0.8))}
    else:
        cfg["piezo"] = {"gain_nm_per_v": round(logu(rng, 15, 150), 5), "f_n_hz": float(rng.uniform(800, 3000)),
                        "zeta": float(rng.uniform(0.6, 0.9))}
    # protocol
    c, m = contact_prefactor(cfg)
    delta0 = d0 + h0
    cfg["delta0_nm"] = delta0
    fr_app = hints.get("app_frac", 0.25)
    fr_ret = hints.get("ret_frac", float(rng.uniform(0.15, 0.25)))
    T_app, T_ret = fr_app * T, fr_ret * T
    T_mid = T - T_app - T_ret
    g0 = float(rng.uniform(0.6, 1.5)) * delta0 + 20.0
    fsi = fs * OS
    ti = np.arange(N * OS) / fsi
    cfg["_ti"] = ti
    t1, t2 = T_app, T_app + T_mid
    x = np.empty_like(ti)
    a = ti < t1
    x[a] = -g0 + (g0 + delta0) * ti[a] / T_app
    mid = (ti >= t1) & (ti < t2)
    tm = ti[mid] - t1
    prot = {"kind": cfg["protocol"], "T_approach_s": T_app, "T_mid_s": T_mid, "T_retract_s": T_ret,
            "start_gap_nm": g0, "setpoint_base_nm": delta0}
    if cfg["protocol"] == "multisine":
        f0 = 1.0 / T_mid
        nl = int(rng.integers(4, 9))
        fmax = min(1300.0, fs / 8)
        cand = [f for f in LINE_CANDIDATES if f <= fmax]
        pick = sorted(rng.choice(cand, size=min(nl, len(cand)), replace=False).tolist())
        if hints.get("slowest_line"):
            pick[0] = f0
        lines = sorted({max(1, int(round(f / f0))) for f in pick})
        if "force_line_hz" in hints:
            lines = sorted(set(lines) | {max(1, int(round(hints["force_line_hz"] / f0)))})
        freqs = [L * f0 for L in lines]
        amps = np.array([1.0 / (i + 3) for i in range(len(freqs))])
        rng.shuffle(amps)
        atot = float(rng.uniform(0.15, 0.4)) * delta0
        amps = amps / amps.sum() * atot
        signs = rng.choice([-1.0, 1.0], size=len(freqs))
        xm = np.full(tm.shape, delta0)
        for f, A, s in zip(freqs, amps, signs):
            xm += s * A * np.sin(2 * np.pi * f * tm)
        x[mid] = xm
        prot.update({"lines_hz": freqs, "amps_nm": amps.tolist(), "signs": signs.tolist()})
        x_end = delta0
    else:
        if rng.random() < 0.5:
            x[mid] = delta0
            prot["step"] = "hold after constant-velocity approach"
        else:
            pre = float(rng.uniform(0.3, 0.6))
            t_s = float(rng.uniform(0.05, 0.2)) * T_mid
            rise = float(rng.uniform(0.001, 0.003))
            # approach reached pre*delta0 ... redo approach to end at pre*delta0
            x[a] = -g0 + (g0 + pre * delta0) * ti[a] / T_app
            r = np.clip((tm - t_s) / rise, 0, 1)
            x[mid] = pre * delta0 + (1 - pre) * delta0 * 0.5 * (1 - np.cos(np.pi * r))
            prot.update({"step": "preload then raised-cosine step", "preload_frac": pre, "t_step_s": t1 + t_s,
                         "rise_s": rise})
        x_end = delta0
    ret = ti >= t2
    g_end = g0 * float(rng.uniform(1.0, 1.3))
    x[ret] = x_end - (x_end + g_end) * (ti[ret] - t2) / T_ret
    cfg["_xcmd"] = x
    cfg["protocol_info"] = prot
    # drive representation
    if cfg["drive_kind"] == "v":
        gain = cfg["piezo"]["gain_nm_per_v"]
        rngx = x.max() - x.min()
        if rngx / gain > 16:
            gain = round(rngx / 16 * 1.05, 5)
            cfg["piezo"]["gain_nm_per_v"] = gain
        v0 = float(rng.uniform(-2, 2)) - (x.max() + x.min()) / 2 / gain
        cfg["drive_offset"] = v0
    else:
        cfg["drive_offset"] = float(rng.uniform(500, 8000))  # nm
    cfg["declare_gain"] = cfg["drive_kind"] == "v" or rng.random() < 0.5
    cfg["has_ref"] = rng.random() < 0.3 and (x.max() / cfg["Ct"] < 9.0)
    cfg["has_height"] = rng.random() < 0.4
    cfg["extra_col"] = rng.random() < 0.15
    cfg["shuffle_cols"] = rng.random() < 0.3
    cfg["_acoustic_white"] = rng.standard_normal(len(ti))
    cfg["_drift_unit"] = drift_unit(rng, ti, hints.get("drift_slow_hz"))
    cfg["sample_name"] = str(rng.choice(["PDMS", "polyacrylamide gel", "agarose gel", "hydrogel",
                                         "fibroblast cell", "polymer brush", "gelatin", "PEG gel"]))
    return cfg


def drift_unit(rng, ti, slow_hz=None):
    """Slow ramp + low-passed random walk, rms 1 over the record (nm when scaled by amp_nm)."""
    T = ti[-1]
    dt = ti[1] - ti[0]
    rw = np.cumsum(rng.standard_normal(len(ti))) * math.sqrt(dt)
    fc = slow_hz if slow_hz else 5.0
    b, a = signal.butter(2, fc / (0.5 / dt))
    rw = signal.lfilter(b, a, rw - rw[0])
    ramp = ti / T * rng.choice([-1, 1]) * rng.uniform(0.5, 1.5)
    u = ramp * (0.0 if slow_hz else 1.0) + rw / (np.std(rw) + 1e-12) * rng.uniform(0.5, 1.0)
    u = u - u[0]
    return u / np.sqrt(np.mean(u ** 2))


# ----------------------------------------------------------------------------- effects
def effect_params(rng, eid, cfg, variant):
    """Initial parameters; the key in AMP is what the sizing loop scales."""
    fs = cfg["fs"]
    if eid == "piezo_hysteresis":
        xpp = float(np.ptp(cfg["_xcmd"]))
        beta = float(rng.uniform(1, 4)) / xpp
        return {"model": "Bouc-Wen (n=1)", "alpha": 0.003, "beta_per_nm": beta,
                "gamma_per_nm": beta * float(rng.uniform(-0.5, 0.8))}
    if eid == "piezo_creep":
        return {"model": "log creep via 11 first-order modes, tau 1 ms..100 s", "gamma": 0.002}
    if eid == "thermal_drift":
        return {"model": "ramp + low-passed random walk on tip-sample distance", "amp_nm": 0.3}
    if eid == "missing_relaxation":
        taus = cfg["prony_tau_s"]
        if variant == "masked":
            j = int(rng.integers(0, 3))
            tau4 = taus[j] * float(rng.uniform(1.8, 2.6)) ** float(rng.choice([-1, 1]))
        else:
            choice = rng.integers(0, 3)
            if choice == 0:
                tau4 = logu(rng, 1.0, 4.0)
            elif choice == 1:
                tau4 = logu(rng, 3e-5, 1.2e-4)
            else:
                tau4 = math.sqrt(taus[0] * taus[1]) * logu(rng, 0.7, 1.4)
        return {"model": "4th Prony term", "J4_frac": 0.01, "tau4_s": tau4}
    if eid == "instrument_resonance":
        if variant == "masked":
            fr = min(float(rng.uniform(0.7, 1.4)) / (2 * math.pi * cfg["prony_tau_s"][2]), 0.3 * fs)
            return {"model": "extra 2nd-order mode on base motion", "f_r_hz": fr, "Q": float(rng.uniform(2, 4)),
                    "kappa": 0.005, "acoustic_frac": 0.0}
        return {"model": "extra 2nd-order mode on base motion", "f_r_hz": float(rng.uniform(300, min(3000, 0.35 * fs))),
                "Q": float(rng.uniform(8, 30)), "kappa": 0.005,
                "acoustic_frac": float(rng.uniform(0.3, 2.0))}
    if eid == "adhesion":
        return {"model": "DMT: constant adhesive force while in contact, snap-off at F_rep=0",
                "F_ad_nN": 0.02 * cfg["F0_nN"]}
    if eid == "tip_geometry":
        if cfg["tip"]["shape"] == "sphere":
            eps = float(rng.choice([-1, 1])) * 0.05
            return {"model": "power-law tip f(r)=B r^(2+eps), Sneddon", "kind": "power_law", "eps": eps,
                    "a_ref_nm": math.sqrt(cfg["tip"]["radius_nm"] * cfg["h0_nm"])}
        return {"model": "sphere-capped (blunted) cone, Sneddon", "kind": "blunted_cone",
                "R_b_nm": 0.05 * cfg["h0_nm"]}
    if eid == "hydrodynamic_drag":
        return {"model": "beta(s)=beta0*h_eff/(s+h_eff) on lever-base velocity",
                "beta0_nN_s_per_nm": 1e-6, "h_eff_nm": float(rng.uniform(3000, 10000))}
    if eid == "channel_delay":
        return {"model": "fractional delay of deflection_v (cubic-spline)", "delay_samples": 0.3}
    if eid == "mains_interference":
        f = float(rng.choice([50.0, 60.0]))
        if variant == "masked" and "mains_f" in cfg:
            f = cfg["mains_f"]
        return {"model": "mains + 2 harmonics", "f_hz": f + float(rng.uniform(-0.03, 0.03)),
                "amp_v": cfg["sigma_v"], "harm_rel": [1.0, float(rng.uniform(0.1, 0.5)), float(rng.uniform(0.05, 0.4))],
                "harm_phase": rng.uniform(0, 2 * np.pi, 3).tolist()}
    if eid == "detector_nonlinearity":
        form = "quadratic" if variant == "masked" else str(rng.choice(["quadratic", "cubic", "tanh"]))
        return {"model": "photodiode response " + form, "form": form, "coef": 1e-3}
    if eid == "substrate_effect":
        return {"model": "bonded thin film bottom-effect correction", "inv_thickness_per_nm": 1.0 / (50 * cfg["h0_nm"])}
    raise KeyError(eid)


AMP = {"piezo_hysteresis": ("alpha", 1e-6, 0.3), "piezo_creep": ("gamma", 1e-6, 0.2),
       "thermal_drift": ("amp_nm", 1e-4, 1e3), "missing_relaxation": ("J4_frac", 1e-6, 2.0),
       "instrument_resonance": ("kappa", 1e-7, 0.5), "adhesion": ("F_ad_nN", 1e-5, 1e3),
       "tip_geometry": ("eps", 1e-5, 0.8), "hydrodynamic_drag": ("beta0_nN_s_per_nm", 1e-12, 1e-2),
       "channel_delay": ("delay_samples", 1e-3, 20.0), "mains_interference": ("amp_v", 1e-7, 1.0),
       "detector_nonlinearity": ("coef", 1e-7, 0.5), "substrate_effect": ("inv_thickness_per_nm", 1e-8, 1.0)}


def amp_key(eid, p):
    if eid == "tip_geometry" and p["kind"] == "blunted_cone":
        return ("R_b_nm", 1e-3, 1e5)
    return AMP[eid]


def contribution_ratio(cfg, eff, v_nom, cont_nom, cache):
    v, cont, *_ = simulate_clean(cfg, eff, cache)
    mask = cont | cont_nom
    diff = (v - v_nom)[mask]
    return float(np.sqrt(np.mean(diff ** 2)) / cfg["sigma_v"]) if mask.any() else 0.0


def size_effect(cfg, eid, p, target, v_nom, cont_nom, cache):
    key, lo, hi = amp_key(eid, p)
    sign = -1.0 if (eid == "tip_geometry" and p.get("eps", 1) < 0) else 1.0
    a = abs(p[key])
    hist = []
    for it in range(8):
        p[key] = sign * a
        r = contribution_ratio(cfg, {eid: p}, v_nom, cont_nom, cache)
        hist.append((a, r))
        if r > 0 and abs(r / target - 1) < 0.04:
            break
        if r <= 0:
            a = min(a * 10, hi)
            continue
        if len(hist) >= 2 and hist[-2][1] > 0 and hist[-2][0] != a and abs(math.log(hist[-1][1] / hist[-2][1])) > 1e-3:
            slope = math.log(hist[-1][1] / hist[-2][1]) / math.log(hist[-1][0] / hist[-2][0])
            slope = min(max(slope, 0.3), 3.0)
        else:
            slope = 1.0
        a = a * (target / r) ** (1.0 / slope)
        a = min(max(a, lo), hi)
    best = min(hist, key=lambda ar: abs(math.log(max(ar[1], 1e-9) / target)))
    p[key] = sign * best[0]
    return best[1]


# ----------------------------------------------------------------------------- noise & output
def pink(rng, n, rms):
    f = np.fft.rfftfreq(n)
    spec = (rng.standard_normal(len(f)) + 1j * rng.standard_normal(len(f)))
    spec[1:] /= np.sqrt(f[1:])
    spec[0] = 0
    x = np.fft.irfft(spec, n)
    return x / np.std(x) * rms


def quant(v):
    return np.round(v / ADC_LSB) * ADC_LSB


def toml_val(v):
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, float):
        return repr(float(v))
    return json.dumps(str(v))


def write_recording(outdir, name, cfg, cols, rng):
    order = list(cols.keys())
    if cfg["shuffle_cols"]:
        rng.shuffle(order)
        order.remove("time_s")
        order.insert(int(rng.integers(0, len(order) + 1)), "time_s")
    fmts = {"time_s": "%.12g", "drive_v": "%.9g", "drive_nm": "%.6f", "deflection_v": "%.8g",
            "reference_deflection_v": "%.8g", "measured_height_nm": "%.5f", "segment": "%d"}
    arr = np.column_stack([cols[c] for c in order])
    with open(os.path.join(outdir, name + ".csv"), "w") as fh:
        fh.write(",".join(order) + "\n")
        np.savetxt(fh, arr, fmt=[fmts[c] for c in order], delimiter=",")
    t = cfg["tip"]
    lines = ['format = "recording/1"', f"sample_rate_hz = {float(cfg['fs'])!r}", "",
             "[cantilever]", f"spring_constant_n_per_m = {float(cfg['k'])!r}",
             f"deflection_sensitivity_nm_per_v = {float(cfg['Ct'])!r}", "", "[tip]", f'shape = "{t["shape"]}"']
    if t["shape"] == "sphere":
        lines.append(f"radius_nm = {float(t['radius_nm'])!r}")
    else:
        lines.append(f"half_angle_deg = {float(t['half_angle_deg'])!r}")
    if cfg["declare_gain"]:
        lines += ["", "[piezo]", f"gain_nm_per_v = {float(cfg['piezo']['gain_nm_per_v'])!r}"]
    lines += ["", "[sample]", f"name = {toml_val(cfg['sample_name'])}", f"poisson_ratio = {float(cfg['nu'])!r}",
              "", "[notes]", 'operator = "blind2 simulator"',
              f'protocol = "{cfg["protocol"]}"', f'generator = "sim.py seed {SEED}"']
    with open(os.path.join(outdir, name + ".toml"), "w") as fh:
        fh.write("\n".join(lines) + "\n")


# ----------------------------------------------------------------------------- case plan
MASK_HINTS = {
    "piezo_hysteresis": ({"protocol": "multisine", "glassy_frac": (0.25, 0.35)},
                         "beside strong viscoelastic loss (glassy fraction 0.25-0.35, multisine loops)"),
    "piezo_creep": ({"protocol": "step", "tau1": (0.3, 1.0)}, "beside a slow retardation time tau1 0.3-1 s in a creep hold"),
    "thermal_drift": ({"protocol": "multisine", "slowest_line": True, "drift_slow_hz": 1.5},
                      "random-walk drift low-passed under the slowest multisine line"),
    "missing_relaxation": ({}, "4th retardation time within x1.8-2.6 of an existing one"),
    "instrument_resonance": ({"protocol": "multisine", "tau3": (0.0003, 0.001)},
                             "low-Q (2-4) mode near the fastest retardation corner 1/(2 pi tau3)"),
    "adhesion": ({"glassy_frac": (0.25, 0.35), "tau1": (0.2, 0.6), "ret_frac": 0.12},
                 "beside viscoelastic retract lag (low glassy fraction, slow tau1, fast retract)"),
    "tip_geometry": ({"protocol": "multisine"}, "small-amplitude multisine: shape mostly absorbed into apparent modulus"),
    "hydrodynamic_drag": ({"tau3": (0.0001, 0.0003)}, "beside a very fast retardation time (viscous-like)"),
    "channel_delay": ({"tau3": (0.0001, 0.0003)}, "beside a very fast retardation time tau3 0.1-0.3 ms"),
    "mains_interference": ({"protocol": "multisine"}, "mains at the frequency of an excitation line"),
    "detector_nonlinearity": ({"d0_range": (100, 300)}, "large deflection range: quadratic response beside Hertz nonlinearity"),
    "substrate_effect": ({"protocol": "step"}, "creep hold: depth-stiffening beside creep; thick film"),
}


def plan_cases(rng):
    cases = []
    # secondary partners: a random derangement so each effect is secondary exactly once
    while True:
        perm = rng.permutation(len(EFFECTS))
        if all(perm[i] != i for i in range(len(EFFECTS))):
            break
    for i, e in enumerate(EFFECTS):
        cases.append({"effects": [e], "variant": "alone", "targets": [float(rng.uniform(1.0, 2.5))]})
        cases.append({"effects": [e], "variant": "masked", "targets": [float(rng.uniform(1.5, 4.0))]})
        cases.append({"effects": [e, EFFECTS[perm[i]]], "variant": "pair",
                      "targets": [float(rng.uniform(1.0, 3.0)), float(rng.uniform(1.0, 3.0))]})
    for _ in range(4):
        cases.append({"effects": [], "variant": "null", "targets": []})
    for _ in range(2):
        cases.append({"effects": [], "variant": "null_pink", "targets": []})
    order = rng.permutation(len(cases))
    cases = [cases[j] for j in order]
    ss = np.random.SeedSequence(SEED).spawn(len(cases))
    for i, c in enumerate(cases):
        c["name"] = f"rec{i + 1:02d}"
        c["seed_seq"] = ss[i]
    return cases


def setup_case(case):
    rng = np.random.default_rng(case["seed_seq"])
    hints = {}
    notes = case["variant"]
    if case["variant"] == "masked":
        hints, mnote = MASK_HINTS[case["effects"][0]]
        hints = dict(hints)
        notes = "masked: " + mnote
    if case["variant"] == "null_pink":
        hints["pink"] = True
    if case["variant"] == "null":
        hints["no_pink"] = True
    if case["variant"] == "alone":
        notes = "alone, near noise floor"
    if case["variant"] == "pair":
        notes = "pair: " + " + ".join(case["effects"])
    if "mains_interference" in case["effects"] and case["variant"] == "masked":
        hints["protocol"] = "multisine"
        mf = float(rng.choice([50.0, 60.0]))
        hints["force_line_hz"] = mf
    if "tip_geometry" in case["effects"] and rng.random() < 0.5:
        hints.setdefault("shape", "cone")
    cfg = gen_nominal(rng, hints)
    if "force_line_hz" in hints:
        cfg["mains_f"] = hints["force_line_hz"]
    return rng, cfg, notes


def run_case(args):
    case, outdir = args
    rng, cfg, notes = setup_case(case)
    cache = {}
    v_nom, cont_nom, d_nom, zb_nom, sens_nom = simulate_clean(cfg, {}, cache)
    eff = {}
    per_ratio = {}
    for eid, tgt in zip(case["effects"], case["targets"]):
        p = effect_params(rng, eid, cfg, case["variant"])
        r = size_effect(cfg, eid, p, tgt, v_nom, cont_nom, cache)
        eff[eid] = p
        per_ratio[eid] = r
    if len(eff) > 1:
        # two effects can cancel (e.g. both mimic a contact-point shift): scale jointly if they do
        r_comb = contribution_ratio(cfg, eff, v_nom, cont_nom, cache)
        target = max(1.2, 0.8 * min(case["targets"]))
        s = 1.0
        for it in range(8):
            if r_comb >= target * 0.95:
                break
            s_new = s * min(max(target / max(r_comb, 1e-3), 1.2), 5.0)
            for eid, p in eff.items():
                key, lo, hi = amp_key(eid, p)
                p[key] = min(max(abs(p[key]) * s_new / s, lo), hi) * (1 if p[key] >= 0 else -1)
            s = s_new
            r_comb = contribution_ratio(cfg, eff, v_nom, cont_nom, cache)
        if s != 1.0:
            for eid, p in eff.items():
                per_ratio[eid] = contribution_ratio(cfg, {eid: p}, v_nom, cont_nom, cache)
            notes += f" (jointly rescaled x{s:.2f}: contributions partly cancel)"
    v, cont, d, zb, sensor = simulate_clean(cfg, eff, cache) if eff else (v_nom, cont_nom, d_nom, zb_nom, sens_nom)
    mask = cont | cont_nom
    ratio = float(np.sqrt(np.mean((v - v_nom)[mask] ** 2)) / cfg["sigma_v"]) if eff else 0.0
    # noise
    N = cfg["N"]
    t = np.arange(N) / cfg["fs"]
    defl = v + rng.standard_normal(N) * cfg["sigma_v"]
    if cfg["pink_rel"] > 0:
        defl = defl + pink(rng, N, cfg["pink_rel"] * cfg["sigma_v"])
    defl = quant(defl)
    cols = {"time_s": t}
    xcmd = cfg["_xcmd"][::OS]
    if cfg["drive_kind"] == "v":
        cols["drive_v"] = xcmd / cfg["piezo"]["gain_nm_per_v"] + cfg["drive_offset"]
    else:
        cols["drive_nm"] = xcmd + cfg["drive_offset"]
    cols["deflection_v"] = defl
    if cfg["has_ref"]:
        # hard reference (sapphire) with the same drive: same actuator/mount effects, no sample effects
        inst = {k: eff[k] for k in ("piezo_hysteresis", "piezo_creep", "instrument_resonance") if k in eff}
        _, zb_ref, _ = stage1(cfg, inst)
        dref = np.maximum(zb_ref, 0.0)
        if "hydrodynamic_drag" in eff:
            pdg = eff["hydrodynamic_drag"]
            zdot = np.gradient(zb_ref, 1.0 / (cfg["fs"] * OS))
            gap = np.maximum(-zb_ref, 0.0)
            dref = dref + np.where(zb_ref <= 0, pdg["beta0_nN_s_per_nm"] * pdg["h_eff_nm"] / (gap + pdg["h_eff_nm"]) * zdot / cfg["k"], 0.0)
        vref = dref / cfg["Ct"] + cfg["offset_v"]
        if "detector_nonlinearity" in eff:
            vref = detector(vref, eff["detector_nonlinearity"])
        if "mains_interference" in eff:
            vref = vref + mains(cfg["_ti"], eff["mains_interference"], phase_shift=float(rng.uniform(0, 6.28)))
        vref = vref[::OS] + rng.standard_normal(N) * cfg["sigma_v"]
        if cfg["pink_rel"] > 0:
            vref = vref + pink(rng, N, cfg["pink_rel"] * cfg["sigma_v"])
        cols["reference_deflection_v"] = quant(vref)
    if cfg["has_height"]:
        sh = logu(rng, 0.1, 0.8)
        cfg["height_sensor_noise_nm"] = sh
        h_off = cfg["drive_offset"] if cfg["drive_kind"] == "nm" else cfg["drive_offset"] * cfg["piezo"]["gain_nm_per_v"]
        cols["measured_height_nm"] = sensor[::OS] + h_off + rng.standard_normal(N) * sh
    if cfg["extra_col"]:
        pi = cfg["protocol_info"]
        seg = np.where(t < pi["T_approach_s"], 0, np.where(t < pi["T_approach_s"] + pi["T_mid_s"], 1, 2))
        cols["segment"] = seg
    write_recording(os.path.join(outdir, "recs"), case["name"], cfg, cols, rng)
    nominal = {k: cfg[k] for k in ("fs", "N", "drive_kind", "k", "Ct", "tip", "nu", "protocol", "h0_nm", "d0_nm",
                                   "F0_nN", "E_relaxed_Pa", "E_instant_Pa", "sigma_nm", "sigma_v", "pink_rel",
                                   "offset_v", "piezo", "delta0_nm", "has_ref", "has_height", "declare_gain",
                                   "drive_offset")}
    # Prony in SI: J (1/Pa) with J_si = J'/( (1-nu^2) 1e9 )
    conv = (1 - cfg["nu"] ** 2) * 1e9
    nominal["prony"] = {"J_glassy_per_Pa": cfg["J_glassy_nm2_per_nN"] / conv,
                        "J_relaxed_per_Pa": cfg["J_relaxed_nm2_per_nN"] / conv,
                        "J_i_per_Pa": [j / conv for j in cfg["prony_J_nm2_per_nN"]],
                        "tau_i_s": cfg["prony_tau_s"],
                        "form": "J(t)=J_glassy+sum J_i(1-exp(-t/tau_i)); J0(relaxed)=J_relaxed"}
    nominal["protocol_info"] = cfg["protocol_info"]
    nominal["contact_fraction"] = float(np.mean(cont_nom))
    if "missing_relaxation" in eff:
        eff["missing_relaxation"]["J4_per_Pa"] = eff["missing_relaxation"]["J4_frac"] * cfg["J_relaxed_nm2_per_nN"] / conv
    return {"name": case["name"], "effects": list(case["effects"]), "ratio": ratio,
            "params": {k: dict(v, ratio_alone=per_ratio[k], target_ratio=tg)
                       for (k, v), tg in zip(eff.items(), case["targets"])},
            "notes": notes, "variant": case["variant"], "nominal": nominal}


def main():
    outdir = sys.argv[1] if len(sys.argv) > 1 else "out"
    os.makedirs(os.path.join(outdir, "recs"), exist_ok=True)
    rng = np.random.default_rng(SEED)
    cases = plan_cases(rng)
    only = os.environ.get("ONLY")
    if only:
        cases = [c for c in cases if c["name"] in only.split(",")]
    nproc = int(os.environ.get("NPROC", "2"))
    args = [(c, outdir) for c in cases]
    if nproc > 1:
        import multiprocessing as mp
        with mp.Pool(nproc) as pool:
            res = []
            for r in pool.imap(run_case, args):
                print(r["name"], r["effects"], round(r["ratio"], 2), flush=True)
                res.append(r)
    else:
        res = []
        for a in args:
            r = run_case(a)
            print(r["name"], r["effects"], round(r["ratio"], 2), flush=True)
            res.append(r)
    res.sort(key=lambda r: r["name"])

    def clean(o):
        if isinstance(o, dict):
            return {k: clean(v) for k, v in o.items()}
        if isinstance(o, (list, tuple)):
            return [clean(v) for v in o]
        if isinstance(o, (np.floating,)):
            return float(o)
        if isinstance(o, (np.integer,)):
            return int(o)
        if isinstance(o, np.bool_):
            return bool(o)
        return o
    if not only:
        with open(os.path.join(outdir, "truth.json"), "w") as fh:
            json.dump(clean(res), fh, indent=1)


if __name__ == "__main__":
    main()
