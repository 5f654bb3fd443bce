#!/usr/bin/env python3
"""Independent AFM indentation recording simulator (blind-sim3).

Usage: python3 sim.py OUTDIR

Writes OUTDIR/recs/recNN.csv + recNN.toml (recording/1 format) and OUTDIR/truth.json.
Written from the spec and the paper notes only; see README.md for the physics.
Internal units: nm, nN, s  (so N/m == nN/nm, Pa == 1e-9 nN/nm^2).
"""
import json
import math
import os
import sys
import time

import numpy as np
from scipy import signal, special

SEED = 31337
CATALOG = [
    "piezo_hysteresis", "piezo_creep", "thermal_drift", "missing_relaxation",
    "instrument_resonance", "adhesion", "tip_geometry", "hydrodynamic_drag",
    "channel_delay", "mains_interference", "detector_nonlinearity", "substrate_effect",
]
PROTOCOLS = ["multisine", "creep", "triangle", "chirp"]
# effects that act after the contact solve (cheap to size)
POST_EFFECTS = {"channel_delay", "mains_interference", "detector_nonlinearity"}


# ----------------------------------------------------------------------------- geometry
class Geometry:
    """Elastic geometry function g(h) = P/E_eff with E_eff = E/(1-nu^2) folded in.

    Lee-Radok (generalised): g(h(t)) = int J(t-s) dP(s), J = creep compliance (1/Pa)."""

    def __init__(self, shape, nu, radius=None, half_angle=None, blunt=None, film=None):
        self.shape, self.nu = shape, nu
        self.radius, self.half_angle, self.blunt, self.film = radius, half_angle, blunt, film
        f = 1.0 / (1.0 - nu * nu)
        self.cs = 4.0 / 3.0 * f * math.sqrt(radius) if shape == "sphere" else None
        if shape == "cone":
            ta = math.tan(math.radians(half_angle))
            self.ta = ta
            self.cc = 2.0 * ta / math.pi * f
            if blunt:
                self.cb = 4.0 / 3.0 * f * math.sqrt(blunt)

    def base(self, h):
        """returns (g, dg/dh) for h > 0 without substrate correction"""
        if self.shape == "sphere":
            s = math.sqrt(h)
            return self.cs * h * s, 1.5 * self.cs * s
        gc, dc = self.cc * h * h, 2.0 * self.cc * h
        if not self.blunt:
            return gc, dc
        s = math.sqrt(h)
        gb, db = self.cb * h * s, 1.5 * self.cb * s
        # smooth maximum (p-norm, p=4) of the sharp-cone and cap-sphere laws
        a4, b4 = gc ** 4, gb ** 4
        tot = a4 + b4
        g = tot ** 0.25
        dg = (a4 / gc * dc + b4 / gb * db) / tot * g if tot > 0 else 0.0
        return g, dg

    def __call__(self, h):
        g, dg = self.base(h)
        if not self.film:
            return g, dg
        t = self.film
        if self.shape == "sphere":
            # bonded incompressible film, Dimitriadis-type polynomial in chi = sqrt(R h)/t
            R = self.radius
            chi = math.sqrt(R * h) / t
            phi = 1 + 1.133 * chi + 1.283 * chi ** 2 + 0.769 * chi ** 3 + 0.0975 * chi ** 4
            dchi = 0.5 * math.sqrt(R / h) / t
            dphi = (1.133 + 2 * 1.283 * chi + 3 * 0.769 * chi ** 2 + 4 * 0.0975 * chi ** 3) * dchi
        else:
            # own quadratic bottom-effect law for a cone: phi = 1 + c1 tan(a) h/t + c2 tan^2(a) (h/t)^2
            q = h / t
            ta = self.ta
            phi = 1 + 0.721 * ta * q + 0.650 * ta * ta * q * q
            dphi = (0.721 * ta + 2 * 0.650 * ta * ta * q) / t
        return g * phi, dg * phi + g * dphi

    def inverse(self, y):
        """numerical inverse of g (vectorised, for protocol design only)"""
        y = np.asarray(y, float)
        hs = np.logspace(-3, 5, 4000)
        gs = np.array([self(h)[0] for h in hs])
        return np.interp(y, gs, hs, left=0.0)


# ----------------------------------------------------------------------------- contact solver
def prony_coeffs(J0, Js, taus, T):
    """exact discretisation of x' = (u - x)/tau for piecewise-linear u (first-order hold)."""
    a = [math.exp(-T / tau) for tau in taus]
    beta = [1.0 - tau / T * (1.0 - ai) for ai, tau in zip(a, taus)]
    b0 = J0 + sum(J * b for J, b in zip(Js, beta))
    return a, beta, b0


def prony_filter(u, J0, Js, taus, T):
    """y = J0 u + sum Ji x_i (vectorised linear response, used for protocol design)"""
    a, beta, _ = prony_coeffs(J0, Js, taus, T)
    y = J0 * u
    for J, ai, bi in zip(Js, a, beta):
        # x_n = a x_{n-1} + bi u_n + (1 - a - bi) u_{n-1}
        x = signal.lfilter([bi, 1 - ai - bi], [1, -ai], u)
        y = y + J * x
    return y


def solve_contact(A, dext_in, dext_out, entry_ok, k, geom, mat, T):
    """Quasi-static cantilever + viscoelastic contact, sample by sample.

    A: base position minus surface position (nm, >0 means pressed past the undeformed surface)
    Returns deflection d (nm), contact mask, contact force P (nN)."""
    J0, Js, taus = mat["J0"], list(mat["Js"]), list(mat["taus"])
    a, beta, b0 = prony_coeffs(J0, Js, taus, T)
    c1 = [1.0 - ai - bi for ai, bi in zip(a, beta)]
    m = len(Js)
    xs = [0.0] * m
    part = [0.0] * m
    alpha = b0 * k
    n = len(A)
    d = np.empty(n)
    P = np.zeros(n)
    inc = np.zeros(n, bool)
    Al = A.tolist(); Di = dext_in.tolist(); Do = dext_out.tolist(); Eo = entry_ok.tolist()
    u_prev = 0.0
    x = 0.0
    was = False
    rng_m = range(m)
    for i in range(n):
        S = 0.0
        for j in rng_m:
            pj = a[j] * xs[j] + c1[j] * u_prev
            part[j] = pj
            S += Js[j] * pj
        Ap = Al[i] - Di[i]
        contact = False
        if Ap > 0.0 and (was or Eo[i]):
            g0, _ = geom(Ap)
            if g0 > S:
                contact = True
        if contact:
            if x <= 0.0 or x >= Ap:
                x = 0.5 * Ap * (g0 - S) / (g0 + alpha * Ap) if g0 > 0 else 0.0
            for _it in range(30):
                h = Ap - x
                gv, dg = geom(h)
                f = gv - alpha * x - S
                xn = x + f / (dg + alpha)
                if xn <= 0.0:
                    xn = 0.5 * x
                elif xn >= Ap:
                    xn = 0.5 * (x + Ap)
                if abs(xn - x) < 1e-9 * (1.0 + abs(x)):
                    x = xn
                    break
                x = xn
            u = k * x
            d[i] = Di[i] + x
        else:
            u = 0.0
            x = 0.0
            d[i] = Do[i]
        for j in rng_m:
            xs[j] = part[j] + beta[j] * u
        u_prev = u
        P[i] = u
        inc[i] = contact
        was = contact
    return d, inc, P


# ----------------------------------------------------------------------------- piezo models
def play_operators(v, radii):
    out = np.empty((len(radii), len(v)))
    vl = v.tolist()
    for j, r in enumerate(radii):
        y = vl[0]
        row = [0.0] * len(vl)
        for i, vi in enumerate(vl):
            lo, hi = vi - r, vi + r
            if y < lo:
                y = lo
            elif y > hi:
                y = hi
            row[i] = y
        out[j] = row
    return out


def lowpass1(v, tau, T):
    a = math.exp(-T / tau)
    zi = signal.lfilter_zi([1 - a], [1, -a]) * v[0]
    return signal.lfilter([1 - a], [1, -a], v, zi=zi)[0]


def lti_from_rest(num, den, v, T):
    # Added by the project, not the simulator's author: B3_STAGE=band_limited applies the
    # stage (and the mount mode) to the drive as the band-limited signal its samples
    # describe, an FFT filter over the drive's even extension, in place of the first-order
    # hold; the README's check of the drive's reading uses it. Unset, the output is as written.
    if os.environ.get("B3_STAGE") == "band_limited":
        v = np.asarray(v, float)
        n = len(v)
        pad = np.concatenate([v, v[::-1]])  # even extension: no jump where it wraps
        s = 2j * np.pi * np.fft.rfftfreq(2 * n, T)
        H = np.polyval(num, s) / np.polyval(den, s)
        return np.fft.irfft(np.fft.rfft(pad) * H, 2 * n)[:n]
    b, a, _ = signal.cont2discrete((num, den), T, method="foh")
    b = np.atleast_1d(np.squeeze(b))
    zi = signal.lfilter_zi(b, a) * v[0]
    return signal.lfilter(b, a, v, zi=zi)[0]


def frac_delay(x, D, L=24):
    """windowed-sinc fractional delay by D samples (causal, edge-padded)."""
    nI = int(math.floor(D))
    fr = D - nI
    n = np.arange(-L, L + 1)
    h = np.sinc(n - fr) * np.blackman(2 * L + 3)[1:-1]
    h /= h.sum()
    xp = np.concatenate([np.full(L + nI, x[0]), x, np.full(L, x[-1])])
    y = np.convolve(xp, h, mode="valid")
    return y[: len(x)]


def pink(rng, n, T, rms):
    w = rng.standard_normal(n)
    F = np.fft.rfft(w)
    f = np.fft.rfftfreq(n, T)
    f[0] = f[1]
    F /= np.sqrt(f / f[1])
    F[0] = 0
    p = np.fft.irfft(F, n)
    return p / p.std() * rms


# ----------------------------------------------------------------------------- protocols
def seg_times(N, weights):
    w = np.array(weights, float)
    b = np.round(np.cumsum(w) / w.sum() * N).astype(int)
    return np.concatenate([[0], b])


def ramp(n, a, b):
    return np.linspace(a, b, n, endpoint=False) if n > 0 else np.zeros(0)


def design_protocol(cfg, rng):
    N, fs, T = cfg["N"], cfg["fs"], 1.0 / cfg["fs"]
    z0 = cfg["z_start"]
    zop = cfg["z_op"]
    proto = cfg["protocol"]
    P = {}
    if proto == "multisine":
        rest = cfg.get("rest_frac", 0.04)
        b = seg_times(N, [rest, 0.18, 0.05, 0.52, 0.08, 0.13 - 0.0])
        n_ex = b[4] - b[3]
        nper = int(rng.integers(2, 5))
        Lp = n_ex // nper
        n_ex = Lp * nper
        f0 = fs / Lp
        nl = int(rng.integers(4, 11))
        fmax = fs / 8
        flo = max(1.0, f0)
        ks = np.unique(np.round(np.logspace(np.log10(flo / f0), np.log10(fmax / f0), nl)).astype(int))
        ks = ks[ks >= 1]
        freqs = ks * f0
        if rng.random() < 0.5:
            amps = np.ones(len(ks))
        else:
            amps = 1.0 / (np.arange(len(ks)) + 3.0)
        ph = -np.pi * np.arange(len(ks)) * (np.arange(len(ks)) + 1) / len(ks)  # Schroeder
        tt = np.arange(n_ex) * T
        ms = sum(a * np.sin(2 * np.pi * f * tt + p) for a, f, p in zip(amps, freqs, ph))
        ms -= sum(a * np.sin(p) for a, p in zip(amps, ph))
        ms *= cfg["exc_amp"] * zop / np.max(np.abs(ms))
        z = np.concatenate([
            np.full(b[1], -z0), ramp(b[2] - b[1], -z0, zop), np.full(b[3] - b[2], zop),
            zop + ms, np.full(b[5] - b[3] - n_ex, zop), ramp(N - b[5], zop, -z0)])
        P.update(lines_hz=[float(x) for x in freqs], periods=nper, period_samples=int(Lp),
                 excitation_start=int(b[3]))
    elif proto == "chirp":
        rest = cfg.get("rest_frac", 0.04)
        b = seg_times(N, [rest, 0.18, 0.05, 0.55, 0.05, 0.13])
        n_ex = b[4] - b[3]
        tt = np.arange(n_ex) * T
        Tc = n_ex * T
        fa = max(1.0, 2.0 / Tc)
        fb = fs / 10
        phase = 2 * np.pi * (fa * tt + 0.5 * (fb - fa) / Tc * tt ** 2)
        ch = np.sin(phase) * signal.windows.tukey(n_ex, 0.04)
        z = np.concatenate([
            np.full(b[1], -z0), ramp(b[2] - b[1], -z0, zop), np.full(b[3] - b[2], zop),
            zop + cfg["exc_amp"] * zop * ch, np.full(b[5] - b[4], zop), ramp(N - b[5], zop, -z0)])
        P.update(f_start_hz=fa, f_stop_hz=fb)
    elif proto == "triangle":
        ncyc = int(rng.integers(2, 5))
        rates = rng.uniform(0.5, 2.0, ncyc)
        rest = cfg.get("rest_frac", 0.03)
        w = [rest, 0.15] + list(0.62 * (1 / rates) / np.sum(1 / rates)) + [0.2]
        b = seg_times(N, w)
        parts = [np.full(b[1], -z0), ramp(b[2] - b[1], -z0, -0.05 * zop)]
        zlo = -0.05 * zop
        tops = rng.uniform(0.6, 1.0, ncyc) * zop
        tops[0] = zop
        for c in range(ncyc):
            n = b[3 + c] - b[2 + c]
            h1 = n // 2
            lo_next = zlo if c < ncyc - 1 else zlo
            parts += [ramp(h1, zlo, tops[c]), ramp(n - h1, tops[c], lo_next)]
        parts.append(ramp(N - b[2 + ncyc], zlo, -z0))
        z = np.concatenate(parts)
        P.update(cycles=ncyc, tops_nm=[float(x) for x in tops])
    elif proto == "creep":
        rest = cfg.get("rest_frac", 0.05)
        b = seg_times(N, [rest, 0.2, 0.55, 0.2])
        # approach ends at the undeformed surface, then a fast force step held by a
        # model-based feed-forward (nominal material, declared tip)
        n_h = b[3] - b[2]
        Fop = cfg["F_op"]
        nr = max(3, int(round(cfg["step_rise_s"] * fs)))
        F = Fop * np.minimum(1.0, np.arange(1, n_h + 1) / nr)
        mat = cfg["mat"]
        y = prony_filter(F, mat["J0"], mat["Js"], mat["taus"], T)
        h = cfg["geom_decl"].inverse(y)
        zh = h + F / cfg["k"]
        z = np.concatenate([np.full(b[1], -z0), ramp(b[2] - b[1], -z0, 0.0), zh,
                            ramp(N - b[3], zh[-1], -z0)])
        P.update(force_setpoint_nN=Fop, step_start=int(b[2]))
    else:
        raise ValueError(proto)
    assert len(z) == N, (proto, len(z), N)
    return z, P


# ----------------------------------------------------------------------------- the instrument
def simulate(cfg, eff):
    """Deterministic part of a recording. eff: {effect_id: params}. Returns dict of arrays."""
    N, T = cfg["N"], 1.0 / cfg["fs"]
    t = np.arange(N) * T
    k = cfg["k"]
    C = cfg["C"]
    v = cfg["z_cmd_q"].copy()  # commanded displacement after DAC quantisation (nm)
    # --- piezo: hysteresis (Prandtl-Ishlinskii), creep (multi-lag), 2nd-order dynamics
    if "piezo_hysteresis" in eff:
        e = eff["piezo_hysteresis"]
        H = cfg["_pi_cache"]
        v = v + e["amp"] * (H - v)
    if "piezo_creep" in eff:
        e = eff["piezo_creep"]
        acc = np.zeros(N)
        for tau in e["taus_s"]:
            acc += lowpass1(v, tau, T) - v
        v = v + e["amp"] * acc / len(e["taus_s"])
    wp = 2 * np.pi * cfg["piezo_fn_hz"]
    zp = lti_from_rest([wp ** 2], [1, 2 * cfg["piezo_zeta"] * wp, wp ** 2], v, T)
    zb = zp
    if "instrument_resonance" in eff:
        e = eff["instrument_resonance"]
        wr = 2 * np.pi * e["f_hz"]
        zr = lti_from_rest([wr ** 2], [1, 2 * e["zeta"] * wr, wr ** 2], zp, T)
        zb = zp + e["amp"] * (zr - zp)
    # --- sample surface (thermal drift moves it) and detector baseline
    zs = np.zeros(N)
    base_v = np.full(N, cfg["offset_v"])
    if "thermal_drift" in eff:
        e = eff["thermal_drift"]
        a = e["amp"]
        zs = zs + a * (e["v_nm_s"] * t + 0.5 * e["acc_nm_s2"] * t ** 2)
        base_v = base_v + a * e["defl_v_per_s"] * t
    A = zb - zs
    # --- external forces: drag (on base velocity), adhesion
    vb = np.gradient(zb, T)
    dext_in = np.zeros(N)
    dext_out = np.zeros(N)
    if "hydrodynamic_drag" in eff:
        e = eff["hydrodynamic_drag"]
        gap = np.maximum(-A, 0.0)
        c = e["amp"] * (e["c_inf"] + e["c_sq"] * e["L_nm"] / (gap + e["L_nm"]))
        fd = c * vb / k
        dext_in += fd
        dext_out += fd
    entry_ok = np.ones(N, bool)
    if "adhesion" in eff:
        e = eff["adhesion"]
        Fa = e["amp"] * e["F_ad_nN"]
        lam = e["lambda_nm"]
        gap0 = np.maximum(-A, 0.0)
        dext_in -= Fa / k
        dext_out -= Fa / k * (lam / (lam + gap0)) ** 2
        # snap-in where the attractive gradient exceeds k: 2 Fa lam^2/(lam+g)^3 = k
        gsnap = max(0.0, (2 * Fa * lam * lam / k) ** (1 / 3) - lam)
        entry_ok = (-A + dext_out) <= gsnap
    # --- material and geometry
    mat = dict(cfg["mat"])
    if "missing_relaxation" in eff:
        e = eff["missing_relaxation"]
        mat = dict(J0=mat["J0"], Js=list(mat["Js"]) + [e["amp"] * e["J_rel"] * mat["J0"]],
                   taus=list(mat["taus"]) + [e["tau_s"]])
    gk = dict(cfg["geom_true_kw"])
    if "tip_geometry" in eff:
        e = eff["tip_geometry"]
        if e["mode"] == "radius":
            gk["radius"] = gk["radius"] * math.exp(e["amp"] * e["log_dir"])
        else:
            gk["blunt"] = e["amp"] * e["cap_nm"]
    if "substrate_effect" in eff:
        e = eff["substrate_effect"]
        gk["film"] = e["thick_nm"] / e["amp"]
    geom = Geometry(**gk)
    d, inc, Pc = solve_contact(A, dext_in, dext_out, entry_ok, k, geom, mat, T)
    # --- hard reference run (same drive, rigid sapphire, same contact point, no drift/adhesion)
    dref = np.maximum(zb, 0.0)
    if "hydrodynamic_drag" in eff:
        dref = np.where(zb > 0, dref, dref + dext_out)
    # --- photodetector
    Vl = d / C + base_v
    Vr = dref / C + cfg["offset_v"]
    if "detector_nonlinearity" in eff:
        e = eff["detector_nonlinearity"]
        Vs = e["vsat_v"] / e["amp"]
        c0 = math.sqrt(math.pi) / 2
        Vl = Vs * special.erf(c0 * Vl / Vs)
        Vr = Vs * special.erf(c0 * Vr / Vs)
    if "mains_interference" in eff:
        e = eff["mains_interference"]
        m = sum(w * np.sin(2 * np.pi * hn * e["f_hz"] * t + p)
                for hn, w, p in zip(e["harmonics"], e["weights"], e["phases"]))
        Vl = Vl + e["amp"] * e["v_amp"] * m
    if "channel_delay" in eff:
        e = eff["channel_delay"]
        Vl = frac_delay(Vl, e["amp"] * e["delay_samples"])
    return dict(V=Vl, Vref=Vr, inc=inc, zp=zp, zb=zb, d=d, P=Pc)


# ----------------------------------------------------------------------------- sizing
def ratio_of(cfg, nom, eff):
    out = simulate(cfg, eff)
    m = nom["inc"]
    diff = (out["V"] - nom["V"])[m]
    return float(np.sqrt(np.mean(diff ** 2)) / cfg["sigma_v"]), out


def size_effect(cfg, nom, name, p, target, max_it=6):
    """scale p['amp'] (log-secant on log ratio vs log amp) so that RMS/sigma hits target."""
    hist = []
    la = math.log(p["amp"])
    for it in range(max_it):
        p["amp"] = math.exp(la)
        r, _ = ratio_of(cfg, nom, {name: p})
        hist.append((la, math.log(max(r, 1e-12))))
        if abs(r / target - 1) < 0.03:
            break
        if len(hist) >= 2 and abs(hist[-1][0] - hist[-2][0]) > 1e-9:
            slope = (hist[-1][1] - hist[-2][1]) / (hist[-1][0] - hist[-2][0])
            if not (0.2 < slope < 5):
                slope = 1.0
        else:
            slope = 1.0
        step = (math.log(target) - hist[-1][1]) / slope
        la = hist[-1][0] + max(-3.0, min(3.0, step))
        if "amp_max" in p:
            la = min(la, math.log(p["amp_max"]))
    # keep the best iterate
    best = min(hist, key=lambda h: abs(h[1] - math.log(target)))
    p["amp"] = math.exp(best[0])
    return math.exp(best[1])


# ----------------------------------------------------------------------------- configuration
def base_config(rng, idx, protocol, fs, N, drive, has_height, has_ref, quirk=None):
    cfg = dict(N=int(N), fs=float(fs), protocol=protocol, drive=drive,
               has_height=has_height, has_ref=has_ref, quirk=quirk)
    T = 1.0 / fs
    # tip
    nu = 0.5 if rng.random() < 0.8 else float(rng.choice([0.45, 0.48, 0.49]))
    cfg["nu"] = nu
    if rng.random() < 0.6:
        R = float(10 ** rng.uniform(1.0, math.log10(5000)))
        gk = dict(shape="sphere", nu=nu, radius=R)
    else:
        ha = float(rng.uniform(15, 40))
        gk = dict(shape="cone", nu=nu, half_angle=ha)
    cfg["geom_true_kw"] = gk
    cfg["geom_decl"] = Geometry(**gk)
    # lever, operating deflection and indentation first; the modulus follows from them
    k = float(10 ** rng.uniform(math.log10(0.01), math.log10(0.5)))
    d_op = rng.uniform(25, 150)
    F_op = k * d_op
    h_op = rng.uniform(20, 250)
    if gk["shape"] == "sphere":
        h_op = min(h_op, max(4.0, 0.4 * gk["radius"]))
    Jmid = cfg["geom_decl"](h_op)[0] / F_op
    # 2-3 Prony terms, tau from ~0.3 ms to 0.5 s
    nterm = int(rng.integers(2, 4))
    slots = [(3e-4, 2e-3), (5e-3, 5e-2), (8e-2, 5e-1)]
    pick = sorted(rng.choice(3, nterm, replace=False)) if nterm < 3 else [0, 1, 2]
    taus = [float(10 ** rng.uniform(math.log10(slots[i][0]), math.log10(slots[i][1]))) for i in pick]
    extra = rng.uniform(0.5, 2.0)
    J0 = Jmid / (1 + 0.5 * extra)
    wts = rng.dirichlet(np.ones(nterm) * 2.0)
    Js = [float(J0 * extra * w) for w in wts]
    cfg["mat"] = dict(J0=float(J0), Js=Js, taus=taus)
    E0 = 1e9 / J0
    names = (["polyacrylamide gel", "hydrogel", "fibroblast"] if E0 < 5e4 else
             ["PDMS", "agarose gel", "soft elastomer"] if E0 < 1e7 else
             ["polystyrene film", "epoxy", "polymer film"])
    cfg["material_name"] = str(rng.choice(names))
    cfg["k"] = k
    cfg["F_op"] = F_op
    cfg["C"] = float(rng.uniform(40, 120))
    cfg["z_op"] = h_op + F_op / k
    cfg["z_start"] = float(rng.uniform(0.6, 2.0) * cfg["z_op"] + rng.uniform(50, 300))
    cfg["exc_amp"] = float(rng.uniform(0.15, 0.3))
    cfg["step_rise_s"] = float(max(2 * T, rng.uniform(2e-4, 2e-3)))
    if quirk == "long_rest":
        cfg["rest_frac"] = 0.35
    # piezo (nominal)
    cfg["piezo_fn_hz"] = float(rng.uniform(2000, 6000))
    cfg["piezo_zeta"] = float(rng.uniform(0.55, 0.85))
    zr = cfg["z_start"] + 1.4 * cfg["z_op"]
    cfg["gain"] = float(max(rng.choice([20.0, 50.0, 100.0, 200.0, 500.0]), zr / 9.0))
    cfg["gain"] = float(round(cfg["gain"], 1))
    # detector
    cfg["sigma_v"] = float(rng.uniform(0.6e-3, 3e-3))
    cfg["adc_bits"] = 16
    cfg["offset_v"] = float(rng.uniform(-0.4, 0.4))
    if quirk == "offset_quant":
        cfg["adc_bits"] = 12
        cfg["offset_v"] = float(rng.choice([-1, 1]) * rng.uniform(3.0, 5.0))
    cfg["pink_rms_v"] = 0.0
    if quirk == "pink":
        cfg["pink_rms_v"] = float(rng.uniform(1.0, 2.0) * cfg["sigma_v"])
    cfg["height_noise_nm"] = float(rng.uniform(0.05, 0.4))
    cfg["z_cmd"], cfg["proto_params"] = design_protocol(cfg, rng)
    # DAC quantisation of the command (20-bit over +-10 V) when the drive is a voltage
    if drive == "drive_v":
        lsb = 20.0 / 2 ** 20
        cfg["drive_volts"] = np.round(cfg["z_cmd"] / cfg["gain"] / lsb) * lsb
        cfg["z_cmd_q"] = cfg["drive_volts"] * cfg["gain"]
    else:
        cfg["z_cmd_q"] = np.round(cfg["z_cmd"], 4)
    return cfg


def effect_params(rng, name, cfg):
    """shape parameters of each effect; 'amp' is the scalar the sizing loop adjusts."""
    fs, T = cfg["fs"], 1.0 / cfg["fs"]
    dur = cfg["N"] * T
    if name == "piezo_hysteresis":
        span = cfg["z_cmd"].max() - cfg["z_cmd"].min()
        radii = list(np.linspace(0, 0.45, 8)[1:] * span)
        w = rng.dirichlet(np.ones(len(radii)))
        cfg["_pi_cache"] = (w[:, None] * play_operators(cfg["z_cmd_q"], radii)).sum(0)
        return dict(amp=0.05, model="Prandtl-Ishlinskii", radii_nm=[float(r) for r in radii],
                    weights=[float(x) for x in w], amp_max=1.0)
    if name == "piezo_creep":
        lo, hi = math.log10(max(5 * T, 1e-3)), math.log10(max(20 * T, dur))
        return dict(amp=0.02, taus_s=[float(x) for x in np.logspace(lo, hi, 5)], amp_max=0.6)
    if name == "thermal_drift":
        return dict(amp=1.0, v_nm_s=float(rng.choice([-1, 1]) * rng.uniform(0.5, 1.5)),
                    acc_nm_s2=float(rng.uniform(-0.5, 0.5) / max(dur, 0.2)),
                    defl_v_per_s=float(rng.uniform(-0.3, 0.3) * 1e-3))
    if name == "missing_relaxation":
        lo, hi = math.log10(max(3 * T, 3e-4)), math.log10(min(dur / 3, 1.0))
        taus = cfg["mat"]["taus"]
        for _ in range(50):
            tx = 10 ** rng.uniform(lo, hi)
            if min(abs(math.log10(tx / t0)) for t0 in taus) > 0.4:
                break
        return dict(amp=0.1, J_rel=1.0, tau_s=float(tx))
    if name == "instrument_resonance":
        f = rng.uniform(0.02, 0.09) * fs
        f = min(f, 4000.0)
        return dict(amp=0.05, f_hz=float(f), zeta=float(rng.uniform(0.01, 0.05)), amp_max=20.0)
    if name == "adhesion":
        return dict(amp=0.2, F_ad_nN=float(cfg["F_op"]), lambda_nm=float(rng.uniform(1.0, 5.0)))
    if name == "tip_geometry":
        if cfg["geom_true_kw"]["shape"] == "sphere":
            return dict(amp=0.1, mode="radius", log_dir=float(rng.choice([-1.0, 1.0])))
        return dict(amp=0.3, mode="blunt", cap_nm=float(rng.uniform(20, 80)))
    if name == "hydrodynamic_drag":
        return dict(amp=1.0, c_inf=1e-6, c_sq=float(rng.uniform(1, 5)) * 1e-6,
                    L_nm=float(rng.uniform(500, 5000)))
    if name == "channel_delay":
        return dict(amp=1.0, delay_samples=1.0, amp_max=8.0)
    if name == "mains_interference":
        f = float(rng.choice([50.0, 60.0]) * rng.uniform(0.998, 1.002))
        harm = [1, 3, 5] if fs > 700 else [1, 3]
        return dict(amp=1.0, f_hz=f, harmonics=harm, v_amp=cfg["sigma_v"],
                    weights=[1.0, float(rng.uniform(0.1, 0.5)), float(rng.uniform(0.0, 0.2))][: len(harm)],
                    phases=[float(x) for x in rng.uniform(0, 2 * np.pi, len(harm))])
    if name == "detector_nonlinearity":
        return dict(amp=0.1, vsat_v=10.0, model="erf (Gaussian spot on split photodiode)")
    if name == "substrate_effect":
        h_op = cfg["z_op"] - cfg["F_op"] / cfg["k"]
        return dict(amp=0.2, thick_nm=float(h_op * rng.uniform(2, 4)), bonded=True)
    raise ValueError(name)


def public_params(p):
    return {k: v for k, v in p.items() if not k.startswith("_") and k != "amp_max"}


# ----------------------------------------------------------------------------- output
def finalize(cfg, out, rng_noise):
    N, T = cfg["N"], 1.0 / cfg["fs"]
    sig = cfg["sigma_v"]
    V = out["V"] + sig * rng_noise.standard_normal(N)
    Vr = out["Vref"] + sig * rng_noise.standard_normal(N)
    if cfg["pink_rms_v"] > 0:
        V = V + pink(rng_noise, N, T, cfg["pink_rms_v"])
    lsb = 20.0 / 2 ** cfg["adc_bits"]
    V = np.clip(np.round(V / lsb) * lsb, -10, 10 - lsb)
    Vr = np.clip(np.round(Vr / lsb) * lsb, -10, 10 - lsb)
    cols = {"time_s": np.arange(N) / cfg["fs"]}
    if cfg["drive"] == "drive_v":
        cols["drive_v"] = cfg["drive_volts"]
    else:
        cols["drive_nm"] = cfg["z_cmd_q"]
    cols["deflection_v"] = V
    if cfg["has_ref"]:
        cols["reference_deflection_v"] = Vr
    if cfg["has_height"]:
        cols["measured_height_nm"] = out["zp"] + cfg["height_noise_nm"] * rng_noise.standard_normal(N)
    return cols


FMT = {"time_s": "%.12g", "drive_v": "%.9g", "drive_nm": "%.4f", "deflection_v": "%.7g",
       "reference_deflection_v": "%.7g", "measured_height_nm": "%.4f"}


def write_csv(path, cols):
    names = list(cols)
    M = np.column_stack([cols[n] for n in names])
    np.savetxt(path, M, delimiter=",", header=",".join(names), comments="",
               fmt=[FMT[n] for n in names])


def write_toml(path, cfg, rng):
    gk = cfg["geom_true_kw"]
    L = ['format = "recording/1"', f"sample_rate_hz = {cfg['fs']:.1f}", "",
         "[cantilever]", f"spring_constant_n_per_m = {cfg['k']:.6g}",
         f"deflection_sensitivity_nm_per_v = {cfg['C']:.6g}", "", "[tip]",
         f'shape = "{gk["shape"]}"']
    if gk["shape"] == "sphere":
        L.append(f"radius_nm = {gk['radius']:.6g}")
    else:
        L.append(f"half_angle_deg = {gk['half_angle']:.6g}")
    L += ["", "[piezo]", f"gain_nm_per_v = {cfg['gain']:.6g}", "", "[sample]",
          f'name = "{cfg["material_name"]}"', f"poisson_ratio = {cfg['nu']:.6g}", "",
          "[notes]", 'operator = "blind-sim3"', f'protocol = "{cfg["protocol"]}"',
          f'instrument = "{rng.choice(["bench-AFM-A", "bench-AFM-B", "liquid-cell rig"])}"']
    if cfg["has_ref"]:
        L.append('reference_sample = "sapphire"')
    with open(path, "w") as f:
        f.write("\n".join(L) + "\n")


# ----------------------------------------------------------------------------- corpus plan
def plan(rng):
    rates = [2000.0, 5000.0, 10000.0, 20000.0, 50000.0]
    items = []
    for e in CATALOG:
        allowed = PROTOCOLS
        if e == "channel_delay":
            allowed = ["multisine", "chirp", "multisine", "chirp"]
        elif e == "instrument_resonance":
            allowed = ["multisine", "chirp", "creep"]
        protos = [str(x) for x in rng.permutation(allowed)][:3]
        for j in range(3):
            items.append(dict(effects=[e], protocol=protos[j]))
    pairs = [("thermal_drift", "adhesion"), ("piezo_hysteresis", "channel_delay"),
             ("missing_relaxation", "mains_interference"), ("substrate_effect", "detector_nonlinearity")]
    for pr in pairs:
        items.append(dict(effects=list(pr), protocol=str(rng.choice(PROTOCOLS))))
    for q in [None, None, "pink", "pink", "offset_quant", "long_rest"]:
        items.append(dict(effects=[], protocol=str(rng.choice(PROTOCOLS)), quirk=q))
    order = rng.permutation(len(items))
    items = [items[i] for i in order]
    for i, it in enumerate(items):
        it["fs"] = float(rng.choice(rates))
        n = int(np.clip(rng.normal(20000, 6000), 8000, 40000))
        it["N"] = n
        it["drive"] = "drive_v" if rng.random() < 0.5 else "drive_nm"
        it["has_height"] = bool(rng.random() < 0.34)
        it["has_ref"] = bool(rng.random() < 0.25)
    return items


def main():
    if len(sys.argv) != 2:
        print(__doc__)
        sys.exit(2)
    outdir = sys.argv[1]
    os.makedirs(os.path.join(outdir, "recs"), exist_ok=True)
    t0 = time.time()
    rng = np.random.default_rng(SEED)
    items = plan(rng)
    truth = []
    for i, it in enumerate(items):
        name = f"rec{i:02d}"
        r = np.random.default_rng([SEED, i])
        cfg = base_config(r, i, it["protocol"], it["fs"], it["N"], it["drive"],
                          it["has_height"], it["has_ref"], it.get("quirk"))
        if it["effects"] and r.random() < 0.3:
            # mild 1/f noise in some effect records too, so 1/f alone does not mark a null
            cfg["pink_rms_v"] = float(r.uniform(0.2, 0.6) * cfg["sigma_v"])
        nom = simulate(cfg, {})
        eff = {}
        ratios = {}
        for e in it["effects"]:
            p = effect_params(r, e, cfg)
            target = float(r.uniform(2.0, 5.0))
            # Added by the project, not the simulator's author: B3_SIZE=LO,HI draws the
            # target ratio from [LO, HI] instead (the same draw scaled), to ask how the
            # diagnosis tells effects apart once they are clearly there. Unset: as written.
            if os.environ.get("B3_SIZE"):
                lo, hi = (float(x) for x in os.environ["B3_SIZE"].split(","))
                target = lo + (target - 2.0) / 3.0 * (hi - lo)
            ratios[e] = size_effect(cfg, nom, e, p, target)
            p["target_ratio"] = target
            p["achieved_ratio_alone"] = ratios[e]
            eff[e] = p
        if eff:
            ratio, out = ratio_of(cfg, nom, eff)
        else:
            ratio, out = 0.0, nom
        cols = finalize(cfg, out, np.random.default_rng([SEED, i, 7]))
        write_csv(os.path.join(outdir, "recs", name + ".csv"), cols)
        write_toml(os.path.join(outdir, "recs", name + ".toml"), cfg, r)
        order = sorted(it["effects"], key=lambda e: -ratios[e])
        mat = cfg["mat"]
        params = dict(
            protocol=cfg["protocol"], protocol_params=cfg["proto_params"], fs_hz=cfg["fs"],
            n_samples=cfg["N"], drive_channel=cfg["drive"], has_measured_height=cfg["has_height"],
            has_reference=cfg["has_ref"], material=dict(J0_nm2_per_nN=mat["J0"], Js=mat["Js"],
                                                        taus_s=mat["taus"],
                                                        E_inst_Pa=1e9 / mat["J0"],
                                                        E_relaxed_Pa=1e9 / (mat["J0"] + sum(mat["Js"]))),
            tip=dict(cfg["geom_true_kw"]), k_n_per_m=cfg["k"], sensitivity_nm_per_v=cfg["C"],
            piezo=dict(gain_nm_per_v=cfg["gain"], fn_hz=cfg["piezo_fn_hz"], zeta=cfg["piezo_zeta"]),
            sigma_white_v=cfg["sigma_v"], pink_rms_v=cfg["pink_rms_v"], adc_bits=cfg["adc_bits"],
            offset_v=cfg["offset_v"], F_op_nN=cfg["F_op"], z_op_nm=cfg["z_op"],
            contact_samples=int(nom["inc"].sum()),
            effects={e: public_params(eff[e]) for e in order})
        notes = "null: clean" if not it["effects"] else "sized against the nominal run"
        if it.get("quirk") == "pink":
            notes = "null: 1/f noise added (not a catalog effect)"
        elif it.get("quirk") == "offset_quant":
            notes = "null quirk: large baseline offset and 12-bit ADC quantisation"
        elif it.get("quirk") == "long_rest":
            notes = "null quirk: long rest out of contact before the approach"
        truth.append(dict(name=name, effects=order, ratio=float(ratio), params=params, notes=notes))
        print(f"{name} {cfg['protocol']:9s} fs={cfg['fs']:7.0f} N={cfg['N']:5d} "
              f"{','.join(order) or '(null)':45s} ratio={ratio:5.2f} t={time.time() - t0:5.1f}s",
              flush=True)
    with open(os.path.join(outdir, "truth.json"), "w") as f:
        json.dump(truth, f, indent=1, default=float)
    print(f"{len(truth)} records in {time.time() - t0:.1f} s")


if __name__ == "__main__":
    main()
