#!/usr/bin/env python3
"""Independent simulator of AFM nanoindentation recordings ("recording/1" format).

Physics chain (all lengths in nm, forces in nN, so K [N/m] = K [nN/nm]):

  command z_cmd (nm)  = gain * drive_v  or  drive_nm
  -> [piezo_hysteresis: Bouc-Wen]  -> [piezo_creep: log creep, bank of first-order lags]
  -> nominal linear actuator dynamics (2nd-order resonance for drive_v, 1st-order lag for drive_nm)
  -> [instrument_resonance: lightly damped stage mode, pole/zero pair]
  -> + [thermal_drift: z drift a1 t + a2 t^2]
  -> tip-sample force balance, time stepped (implicit, exact FOH Prony update each step):
        K d = P_rep - F_ad + F_drag,   h = z - d,
        Phi(h) = (J * dP_rep)(t)       (Lee-Radok, J(t) = J0 + sum Ji (1 - exp(-t/tau_i)))
        Phi = elastic shape function: P = E * Phi(h)   (sphere 4 sqrt(R) h^1.5 / (3(1-nu^2)),
              cone 2 tan(a) h^2 / (pi (1-nu^2)); tip_geometry / substrate_effect modify Phi)
  -> deflection d (nm) + [thermal_drift: deflection baseline drift] -> volts (/C_t)
  -> [detector_nonlinearity: v + c2 v^2 + c3 v^3] -> [+ mains_interference]
  -> sampled (with [channel_delay]: deflection channels lag the drive channel)
  -> + white detector noise (+ optional 1/f noise).

Run:  python3 sim.py OUTDIR      (see gen.sh)
"""
import csv
import json
import math
import os
import sys

import numpy as np
from scipy import signal

SEED = 20240607
N_SAMPLES = 20000

EFFECTS = ["piezo_hysteresis", "piezo_creep", "thermal_drift", "missing_relaxation",
           "instrument_resonance", "adhesion", "tip_geometry", "hydrodynamic_drag",
           "channel_delay", "mains_interference", "detector_nonlinearity", "substrate_effect"]


# ----------------------------------------------------------------------------------------
# Contact shape functions Phi(h): elastic P = E * Phi(h) (units: Phi in nm^2 when h, R in nm;
# then P[nN] = E[Pa] * Phi[nm^2] * 1e-9).
# ----------------------------------------------------------------------------------------
class PowerPhi:
    """Phi(h) = c h^p * C(chi), chi = kap * h^q (substrate correction, Dimitriadis polynomial)."""

    SUB = (1.133, 1.283, 0.769, 0.0975)

    def __init__(self, c, p, kap=0.0, q=1.0):
        self.c, self.p, self.kap, self.q = c, p, kap, q

    def f(self, h):
        if h <= 0.0:
            return 0.0, 0.0
        c, p = self.c, self.p
        base = c * h ** p
        dbase = p * base / h
        if self.kap == 0.0:
            return base, dbase
        chi = self.kap * h ** self.q
        a1, a2, a3, a4 = self.SUB
        C = 1.0 + chi * (a1 + chi * (a2 + chi * (a3 + chi * a4)))
        dC = a1 + chi * (2 * a2 + chi * (3 * a3 + chi * 4 * a4))
        dchi = self.q * chi / h
        return base * C, dbase * C + base * dC * dchi

    def inv(self, y):
        if y <= 0.0:
            return 0.0
        h = (y / self.c) ** (1.0 / self.p)
        if self.kap == 0.0:
            return h
        lo, hi = 0.0, h
        for _ in range(80):
            mid = 0.5 * (lo + hi)
            if self.f(mid)[0] < y:
                lo = mid
            else:
                hi = mid
        return 0.5 * (lo + hi)


class TablePhi:
    """Phi(h) tabulated on a grid uniform in sqrt(h), linear interpolation."""

    def __init__(self, h_of_a, phi_of_a, hmax, n=40000):
        self.du = math.sqrt(hmax) / (n - 1)
        hg = (np.arange(n) * self.du) ** 2
        self.h = hg.tolist()
        self.phi = np.interp(hg, h_of_a, phi_of_a).tolist()
        self.phi_arr = np.asarray(self.phi)
        self.hg = hg
        self.n = n

    def f(self, h):
        if h <= 0.0:
            return 0.0, 0.0
        i = int(math.sqrt(h) / self.du)
        if i >= self.n - 1:
            i = self.n - 2
        h0, h1 = self.h[i], self.h[i + 1]
        p0, p1 = self.phi[i], self.phi[i + 1]
        s = (p1 - p0) / (h1 - h0)
        return p0 + s * (h - h0), s

    def inv(self, y):
        if y <= 0.0:
            return 0.0
        return float(np.interp(y, self.phi_arr, self.hg))


class ScaledPhi:
    def __init__(self, phi, k):
        self.phi, self.k = phi, k

    def f(self, h):
        p, dp = self.phi.f(h)
        return self.k * p, self.k * dp

    def inv(self, y):
        return self.phi.inv(y / self.k)


def mdr_phi_flat_paraboloid(R, a0, nu, hmax):
    """Worn tip: paraboloid of radius R truncated by a flat of radius a0 (MDR / Sneddon)."""
    k = 2.0 / (1.0 - nu ** 2)
    amax = a0 + 1.0
    while (amax / R) * math.sqrt(amax ** 2 - a0 ** 2) < hmax * 1.05:
        amax *= 1.5
    a = a0 + (amax - a0) * np.linspace(0, 1, 200001) ** 2
    w = np.sqrt(np.maximum(a ** 2 - a0 ** 2, 0.0))
    h = a / R * w
    phi = k / R * (a ** 2 * w - w ** 3 / 3.0)
    return TablePhi(h, phi, hmax)


def mdr_phi_blunted_cone(alpha, Rb, nu, hmax):
    """Cone (half angle alpha) with a paraboloidal apex of radius Rb, tangent at r_t = Rb cot(alpha)."""
    k = 2.0 / (1.0 - nu ** 2)
    cot = 1.0 / math.tan(alpha)
    rt = Rb * cot
    amax = max(2 * rt, 2 * hmax * math.tan(alpha)) * 2.0
    x = amax * np.linspace(0, 1, 400001) ** 2
    g = np.empty_like(x)
    m = x <= rt
    g[m] = x[m] ** 2 / Rb
    xm = x[~m]
    th = np.arcsin(rt / xm)
    g[~m] = xm * ((xm / Rb) * (1 - np.cos(th)) + cot * (np.pi / 2 - th))
    G = np.concatenate([[0.0], np.cumsum(0.5 * (g[1:] + g[:-1]) * np.diff(x))])
    phi = k * (x * g - G)
    return TablePhi(g, phi, hmax)


# ----------------------------------------------------------------------------------------
# Linear filters
# ----------------------------------------------------------------------------------------
def lti_filter(num, den, x, dt):
    """Simulate continuous H(s)=num/den (unity DC gain assumed) on samples x (FOH-exact),
    starting from steady state at x[0]."""
    bd, ad, _ = signal.cont2discrete((num, den), dt, method="foh")
    bd = np.atleast_1d(np.squeeze(bd))
    ad = np.atleast_1d(np.squeeze(ad))
    x0 = x[0]
    y = signal.lfilter(bd, ad, x - x0)
    return y + x0


def foh_coeffs(tau, dt):
    a = math.exp(-dt / tau)
    b = (tau / dt) * (1 - a) - a
    g = 1 - (tau / dt) * (1 - a)
    return a, b, g


def first_order_bank(x, taus, dt):
    """sum_k lowpass_tau_k(x - x0)  (exact for piecewise-linear input)."""
    out = np.zeros_like(x)
    x = x - x[0]
    for tau in taus:
        a, b, g = foh_coeffs(tau, dt)
        out += signal.lfilter([g, b], [1.0, -a], x)
    return out


def bouc_wen(z, alpha, L):
    """Bouc-Wen hysteresis state on displacement command z (nm): dh = alpha dz - beta|dz|h - gamma dz|h|."""
    beta = gamma = 1.0 / (2.0 * L)
    h = 0.0
    out = np.empty_like(z)
    zl = z.tolist()
    prev = zl[0]
    for i, zi in enumerate(zl):
        dz = zi - prev
        prev = zi
        h += alpha * dz - beta * abs(dz) * h - gamma * dz * abs(h)
        out[i] = h
    return out


def pink_noise(rng, n, rms):
    w = rng.standard_normal(n)
    W = np.fft.rfft(w)
    f = np.arange(len(W), dtype=float)
    f[0] = 1.0
    W = W / np.sqrt(f)
    W[0] = 0.0
    x = np.fft.irfft(W, n)
    return x * (rms / np.sqrt(np.mean(x ** 2)))


# ----------------------------------------------------------------------------------------
# Contact force balance, time stepped
# ----------------------------------------------------------------------------------------
def contact_sim(zrel, fext, dt, J0n, Jn, taus, phi, K, Fad=0.0, lam=1.0):
    """zrel: base position relative to undeformed surface (nm, + = into sample); fext: drag force
    (nN, + = pushes tip away from sample). J*n in nm^2/nN. Returns d (nm), u=P_rep (nN), contact."""
    n = len(zrel)
    co = [foh_coeffs(t, dt) for t in taus]
    al = [c[0] for c in co]
    be = [c[1] for c in co]
    ga = [c[2] for c in co]
    m = len(taus)
    A = J0n + sum(Jn[i] * ga[i] for i in range(m))
    x = [0.0] * m
    uprev = 0.0
    d = np.empty(n)
    uu = np.empty(n)
    cont = np.zeros(n, dtype=bool)
    zl = zrel.tolist()
    fl = fext.tolist()
    invK = 1.0 / K
    pf = phi.f
    rng_m = range(m)
    for k in range(n):
        B = 0.0
        for i in rng_m:
            B += Jn[i] * (al[i] * x[i] + be[i] * uprev)
        z = zl[k]
        fe = fl[k]
        q = z + (Fad - fe) * invK  # tip depth if P_rep = 0
        u = 0.0
        incontact = False
        if q > 0.0:
            p0, _ = pf(q)
            if p0 > B:
                incontact = True
                lo, hi = 0.0, K * q
                u = uprev if lo < uprev < hi else 0.5 * (lo + hi)
                tol = 1e-12 * hi + 1e-15
                for _ in range(60):
                    p, dp = pf(q - u * invK)
                    F = p - A * u - B
                    if F > 0:
                        lo = u
                    else:
                        hi = u
                    dF = -dp * invK - A
                    un = u - F / dF
                    if not (lo < un < hi):
                        un = 0.5 * (lo + hi)
                    if abs(un - u) < tol:
                        u = un
                        break
                    u = un
        if incontact:
            d[k] = (u - Fad + fe) * invK
        else:
            if Fad > 0.0:
                s = phi.inv(B) if B > 0 else 0.0
                gap = s - z
                if gap < 0:
                    gap = 0.0
                d[k] = (-Fad * math.exp(-gap / lam) + fe) * invK
            else:
                d[k] = fe * invK
        uu[k] = u
        cont[k] = incontact
        for i in rng_m:
            x[i] = al[i] * x[i] + be[i] * uprev + ga[i] * u
        uprev = u
    return d, uu, cont


# ----------------------------------------------------------------------------------------
# Protocol
# ----------------------------------------------------------------------------------------
class Protocol:
    """z_rel(t) command relative to the sample surface (nm, + = toward/into the sample)."""

    def __init__(self, rng, T, z_above, z_pre, z_end, kind, fs):
        self.T = T
        self.kind = kind
        self.t1 = 0.03 * T
        self.t2 = 0.20 * T
        self.t3 = 0.23 * T
        self.t4 = 0.78 * T
        self.t5 = 0.95 * T
        self.z_above, self.z_pre, self.z_end = z_above, z_pre, z_end
        Texc = self.t4 - self.t3
        self.taper = 0.03
        if kind == "multisine":
            fmin = max(2.0, 2.0 / Texc)
            fmax = min(1000.0, 0.2 * fs)
            nl = int(rng.integers(4, 8))
            grid = np.geomspace(fmin, fmax, nl) * np.exp(rng.uniform(-0.15, 0.15, nl))
            grid[0], grid[-1] = fmin * rng.uniform(1.0, 1.3), fmax * rng.uniform(0.85, 1.0)
            df = 1.0 / Texc
            fr = np.unique(np.maximum(np.round(grid / df), 1) * df)
            self.freqs = fr
            self.amps = rng.uniform(0.5, 1.0, len(fr))
            self.phases = rng.uniform(0, 2 * np.pi, len(fr))
            tt = np.linspace(0, Texc, 20001)
            ms = self._ms(tt)
            self.scale = rng.uniform(0.25, 0.42) * z_pre / np.max(np.abs(ms))
            self.params = dict(kind=kind, freqs_hz=[float(f) for f in fr],
                               amps_nm=[float(a * self.scale) for a in self.amps],
                               phases_rad=[float(p) for p in self.phases])
        else:
            self.step = rng.uniform(0.2, 0.4) * z_pre * (1 if rng.random() < 0.7 else -1)
            self.rise = rng.uniform(2e-3, 8e-3)
            self.ts_up = self.t3 + 0.05 * Texc
            self.ts_dn = self.t3 + rng.uniform(0.5, 0.65) * Texc
            self.params = dict(kind=kind, step_nm=float(self.step), rise_s=float(self.rise),
                               t_step_up_s=float(self.ts_up), t_step_down_s=float(self.ts_dn))
        self.params.update(dict(z_above_nm=float(z_above), z_pre_nm=float(z_pre), z_end_nm=float(z_end),
                                t_approach=[float(self.t1), float(self.t2)], t_excite=[float(self.t3), float(self.t4)],
                                t_retract=[float(self.t4), float(self.t5)]))

    def _ms(self, tau):
        s = np.zeros_like(tau)
        for f, a, p in zip(self.freqs, self.amps, self.phases):
            s += a * np.sin(2 * np.pi * f * tau + p)
        return s

    def __call__(self, t):
        t = np.asarray(t, dtype=float)
        z = np.interp(t, [self.t1, self.t2, self.t4, self.t5],
                      [-self.z_above, self.z_pre, self.z_pre, -self.z_end])
        m = (t > self.t3) & (t < self.t4)
        tm = t[m] - self.t3
        if self.kind == "multisine":
            Texc = self.t4 - self.t3
            w = np.ones_like(tm)
            a = tm < self.taper
            w[a] = 0.5 - 0.5 * np.cos(np.pi * tm[a] / self.taper)
            b = tm > Texc - self.taper
            w[b] = 0.5 - 0.5 * np.cos(np.pi * (Texc - tm[b]) / self.taper)
            z[m] += self.scale * w * self._ms(tm)
        else:
            tt = t[m]
            up = np.clip((tt - self.ts_up) / self.rise, 0, 1)
            dn = np.clip((tt - self.ts_dn) / self.rise, 0, 1)
            z[m] += self.step * (up - dn)
        return z


# ----------------------------------------------------------------------------------------
# One recording
# ----------------------------------------------------------------------------------------
class Recording:
    def __init__(self, spec, seed):
        self.spec = spec
        rng = np.random.default_rng(seed)
        self.rng = rng
        self.fs = float(spec["fs"])
        self.N = N_SAMPLES
        self.T = self.N / self.fs
        # Internal oversampling. SIM_OS_FACTOR (added by viscoprobe, not by the author)
        # overrides it: at 2x the simulator's own discretisation error is a systematic
        # residual that can hide effects near the floor; 8x makes it small.
        self.os = int(os.environ.get("SIM_OS_FACTOR", 2 if self.fs < 10000 else 1))
        self.dt = 1.0 / (self.fs * self.os)
        self.t_out = np.arange(self.N) / self.fs
        self.t_int = np.arange(self.N * self.os) * self.dt
        self.nu = float(spec.get("nu", 0.5))
        self.tip = spec["tip"]
        # draw instrument + sample until the (linearised) excitation SNR is paper-like (60..300)
        for attempt in range(500):
            self._draw_geometry(rng, spec)
            if 60 <= self.snr_pred <= 300:
                break
        z_above = float(rng.uniform(100, 300))
        z_end = float(rng.uniform(100, 250))
        self.proto = Protocol(rng, self.T, z_above, self.z_pre, z_end, spec["exc"], self.fs)
        self.drive_kind = spec["drive"]
        if self.drive_kind == "v":
            self.gain = float(rng.uniform(20, 100))
            self.z_surf = float(rng.uniform(3, 6)) * self.gain
            self.act_f = float(rng.uniform(5000, 10000))
            self.act_zeta = float(rng.uniform(0.4, 0.7))
        else:
            self.gain = float(rng.uniform(20, 100))
            self.z_surf = float(rng.uniform(800, 3000))
            self.act_f = float(rng.uniform(3000, 6000))
            self.act_zeta = None
        # noise
        self.sig_h = float(rng.uniform(0.1, 0.4))
        self.pink_ratio = float(spec.get("pink", 0.0)) * float(rng.uniform(0.8, 1.5)) if spec.get("pink") else 0.0
        self.phase_ref_mains = float(rng.uniform(0, 2 * np.pi))
        # default effect parameter shapes (strength to be tuned)
        self.eff = {}
        for e in spec["effects"]:
            self.eff[e] = self.default_effect(e, rng)
        self.noise_seed = int(rng.integers(0, 2 ** 31))

    def _draw_geometry(self, rng, spec):
        self.K = float(np.exp(rng.uniform(np.log(0.05), np.log(0.5))))
        self.C = float(rng.uniform(50, 100))
        rk = float(np.exp(rng.uniform(np.log(0.5), np.log(4.0))))
        if self.tip == "sphere":
            self.R = float(spec.get("R", np.exp(rng.uniform(np.log(150), np.log(1000)))))
            h_op = float(min(rng.uniform(50, 250), 0.3 * self.R))
            a = math.sqrt(self.R * h_op) * 1e-9
            Estar = rk * self.K / (2 * a)
            self.phi_c = 4 * math.sqrt(self.R) / (3 * (1 - self.nu ** 2))
            self.phi_p = 1.5
        else:
            self.alpha_deg = float(rng.uniform(15, 35))
            al = math.radians(self.alpha_deg)
            h_op = float(rng.uniform(80, 250))
            Estar = rk * self.K * math.pi / (4 * math.tan(al) * h_op * 1e-9)
            self.phi_c = 2 * math.tan(al) / (math.pi * (1 - self.nu ** 2))
            self.phi_p = 2.0
        E = float(np.clip(Estar * (1 - self.nu ** 2), 1e4, 1e7))
        self.h_op = h_op
        # Prony creep compliance J(t) = J0 + sum Ji (1 - exp(-t/tau_i)), J in 1/Pa
        self.J0 = 1.0 / E
        tot = self.J0 * rng.uniform(0.6, 2.0)
        w = rng.dirichlet([2, 2, 2])
        self.Ji = [float(tot * x) for x in w]
        self.taus = [float(np.exp(rng.uniform(np.log(4e-4), np.log(1.5e-3)))),
                     float(np.exp(rng.uniform(np.log(4e-3), np.log(2e-2)))),
                     float(np.exp(rng.uniform(np.log(6e-2), np.log(0.5))))]
        Jmid = self.J0 + 0.5 * tot
        P_op = self.phi_c * h_op ** self.phi_p / (Jmid * 1e9)  # nN
        self.z_pre = h_op + P_op / self.K
        # white deflection noise: cantilever thermal noise sqrt(kB T / K) times a detector factor
        self.noise_nm = math.sqrt(4.1e-21 / self.K) * 1e9 * float(rng.uniform(0.8, 1.6))
        kc = self.phi_p * P_op / h_op
        self.snr_pred = 0.33 * self.z_pre * (kc / (kc + self.K)) / 2.5 / self.noise_nm

    # -------------------------------------------------------------------------------
    def default_effect(self, e, rng):
        if e == "piezo_hysteresis":
            return dict(alpha=0.03, L_nm=float(rng.uniform(80, 250)))
        if e == "piezo_creep":
            return dict(gamma_per_decade=0.01, taus_s=[5e-3, 5e-2, 0.5, 5.0, 50.0])
        if e == "thermal_drift":
            sgn = 1 if rng.random() < 0.5 else -1
            return dict(z_rate_nm_s=sgn * rng.uniform(0.5, 1.0), z_accel_nm_s2=float(rng.uniform(-0.5, 0.5) / self.T),
                        defl_rate_nm_s=float(rng.uniform(-0.7, 0.7)), scale=1.0)
        if e == "missing_relaxation":
            if self.spec.get("mr_kind", "slow") == "slow":
                tau = float(rng.uniform(1.0, 3.0))
            else:  # "mid": in the log-gap between the 2nd and 3rd retardation times
                tau = float(np.sqrt(self.taus[1] * self.taus[2]) * np.exp(rng.uniform(-0.2, 0.2)))
            return dict(J_extra_over_J0=0.1, tau_extra_s=tau)
        if e == "instrument_resonance":
            fmax = min(900.0, 0.15 * self.fs)
            f = float(rng.uniform(150, fmax)) if self.proto.kind == "multisine" else float(rng.uniform(50, 130))
            if self.proto.kind == "multisine":  # stage mode close to one of the excited lines
                fl = [x for x in self.proto.freqs if 150 <= x <= fmax]
                if fl:
                    f = float(rng.choice(fl) * rng.uniform(0.9, 1.1))
            zp = float(rng.uniform(0.015, 0.04)) if self.proto.kind == "multisine" else float(rng.uniform(0.006, 0.015))
            return dict(f_mode_hz=f, zeta_pole=zp, zeta_zero_excess=1.0)
        if e == "adhesion":
            return dict(F_ad_nN=0.5, lambda_nm=float(rng.uniform(1.0, 3.0)))
        if e == "tip_geometry":
            if self.tip == "sphere":
                return dict(kind="flat_worn_paraboloid", flat_radius_nm=0.2 * math.sqrt(self.R * self.h_op))
            # flank profile f(r) = B r^n (n = 1: the nominal cone); n > 1: apex region blunter,
            # giving P ~ h^(1 + 1/n) instead of h^2
            return dict(kind="power_law_profile", profile_exponent_n=1.05)
        if e == "hydrodynamic_drag":
            return dict(b0_N_s_per_m=1e-7, L_nm=200.0, near_surface_gain=1.0)
        if e == "channel_delay":
            return dict(delay_s=0.5 / self.fs)
        if e == "mains_interference":
            f0 = float(self.spec.get("mains_f", 50.0)) + float(rng.uniform(-0.03, 0.03))
            return dict(f0_hz=f0, amp_v=1e-3, harm_rel=[1.0, float(rng.uniform(0.1, 0.5)), float(rng.uniform(0.2, 0.6))],
                        phases_rad=[float(x) for x in rng.uniform(0, 2 * np.pi, 3)])
        if e == "detector_nonlinearity":
            return dict(scale=0.01, q2=float(rng.choice([-1, 1]) * rng.uniform(0.5, 1.0)), q3=float(-rng.uniform(0.0, 0.6)))
        if e == "substrate_effect":
            return dict(thickness_nm=20.0 * self.h_op)
        raise ValueError(e)

    STRENGTH = {"piezo_hysteresis": "alpha", "piezo_creep": "gamma_per_decade", "thermal_drift": "scale",
                "missing_relaxation": "J_extra_over_J0", "instrument_resonance": "zeta_zero_excess",
                "adhesion": "F_ad_nN", "tip_geometry": None, "hydrodynamic_drag": "b0_N_s_per_m",
                "channel_delay": "delay_s", "mains_interference": "amp_v", "detector_nonlinearity": "scale",
                "substrate_effect": None}

    def get_strength(self, e):
        p = self.eff[e]
        if e == "tip_geometry":
            return p["flat_radius_nm"] if "flat_radius_nm" in p else p["profile_exponent_n"] - 1.0
        if e == "substrate_effect":
            return 1.0 / p["thickness_nm"]
        return p[self.STRENGTH[e]]

    def set_strength(self, e, s):
        p = self.eff[e]
        if e == "tip_geometry":
            if "flat_radius_nm" in p:
                p["flat_radius_nm"] = float(s)
            else:
                p["profile_exponent_n"] = float(1.0 + s)
        elif e == "substrate_effect":
            p["thickness_nm"] = float(1.0 / s)
        else:
            p[self.STRENGTH[e]] = float(s)

    # -------------------------------------------------------------------------------
    def zcmd_abs(self, t):
        return self.z_surf + self.proto(t)

    def actuator(self, t, active):
        """actual actuator position (absolute nm) for command evaluated at times t."""
        z = self.zcmd_abs(t)
        if "piezo_hysteresis" in active:
            p = self.eff["piezo_hysteresis"]
            z = z - bouc_wen(z, p["alpha"], p["L_nm"])
        if "piezo_creep" in active:
            p = self.eff["piezo_creep"]
            zc = z - z[0]
            z = z + p["gamma_per_decade"] * first_order_bank(zc + z[0], p["taus_s"], self.dt)
        w = 2 * np.pi * self.act_f
        if self.drive_kind == "v":
            z = lti_filter([w * w], [1, 2 * self.act_zeta * w, w * w], z, self.dt)
        else:
            z = lti_filter([w], [1, w], z, self.dt)
        if "instrument_resonance" in active:
            p = self.eff["instrument_resonance"]
            wm = 2 * np.pi * p["f_mode_hz"]
            zp = p["zeta_pole"]
            zz = zp * (1 + p["zeta_zero_excess"])
            z = lti_filter([1, 2 * zz * wm, wm * wm], [1, 2 * zp * wm, wm * wm], z, self.dt)
        return z

    def make_phi(self, active, hmax):
        """Shape function of the real contact. For tip_geometry and substrate_effect the real
        Phi is rescaled to equal the nominal Phi at the operating depth h_op (equivalently the
        true material compliance is J * k): the effect is the depth dependence only."""
        nu = self.nu
        nominal = PowerPhi(self.phi_c, self.phi_p)
        real = None
        if "tip_geometry" in active:
            p = self.eff["tip_geometry"]
            if p["kind"] == "flat_worn_paraboloid":
                real = mdr_phi_flat_paraboloid(self.R, p["flat_radius_nm"], nu, hmax)
            elif p["kind"] == "power_law_profile":
                real = PowerPhi(self.phi_c, 1.0 + 1.0 / p["profile_exponent_n"])
            else:
                real = mdr_phi_blunted_cone(math.radians(self.alpha_deg), p["apex_radius_nm"], nu, hmax)
        elif "substrate_effect" in active:
            t = self.eff["substrate_effect"]["thickness_nm"]
            if self.tip == "sphere":
                real = PowerPhi(self.phi_c, self.phi_p, kap=math.sqrt(self.R) / t, q=0.5)
            else:
                real = PowerPhi(self.phi_c, self.phi_p, kap=2 * math.tan(math.radians(self.alpha_deg)) / (math.pi * t), q=1.0)
        if real is None:
            return nominal
        k = nominal.f(self.h_op)[0] / real.f(self.h_op)[0]
        for e in ("tip_geometry", "substrate_effect"):
            if e in active:
                self.eff[e]["compliance_scale_k"] = float(k)
        return ScaledPhi(real, k)

    def simulate(self, active):
        """Noise-free simulation with the given set of active effects. Returns dict of channels
        on the output grid (deflection_v, reference_deflection_v, height_nm) and internals."""
        active = set(active)
        delay = self.eff["channel_delay"]["delay_s"] if "channel_delay" in active else 0.0
        t_phys = self.t_int - delay
        z_abs = self.actuator(t_phys, active)
        z_abs_nodelay = self.actuator(self.t_int, active) if delay else z_abs
        zrel = z_abs - self.z_surf
        drift = np.zeros_like(zrel)
        ddrift = np.zeros_like(zrel)
        if "thermal_drift" in active:
            p = self.eff["thermal_drift"]
            s = p["scale"]
            drift = s * (p["z_rate_nm_s"] * t_phys + p["z_accel_nm_s2"] * t_phys ** 2)
            ddrift = s * p["defl_rate_nm_s"] * t_phys
        zc = zrel + drift
        fext = np.zeros_like(zc)
        if "hydrodynamic_drag" in active:
            p = self.eff["hydrodynamic_drag"]
            vel = np.gradient(z_abs, self.dt)  # nm/s, + toward sample
            gap = np.maximum(-zc, 0.0)
            b = p["b0_N_s_per_m"] * (1 + p["near_surface_gain"] * p["L_nm"] / (gap + p["L_nm"]))
            fext = b * vel  # N s/m * nm/s = nN
        J0 = self.J0
        Ji = list(self.Ji)
        taus = list(self.taus)
        if "missing_relaxation" in active:
            p = self.eff["missing_relaxation"]
            Ji.append(p["J_extra_over_J0"] * self.J0)
            taus.append(p["tau_extra_s"])
        hmax = 3.0 * (np.max(zc) + 50.0)
        phi = self.make_phi(active, hmax)
        Fad = self.eff["adhesion"]["F_ad_nN"] if "adhesion" in active else 0.0
        lam = self.eff["adhesion"]["lambda_nm"] if "adhesion" in active else 1.0
        d, u, cont = contact_sim(zc, fext, self.dt, J0 * 1e9, [j * 1e9 for j in Ji], taus, phi, self.K, Fad, lam)
        d = d + ddrift
        # hard reference: same actuator (no drift, no sample), contact at z_rel = 0
        dref = np.maximum(zrel, 0.0)
        if "hydrodynamic_drag" in active:
            dref = np.where(zrel > 0, dref, fext / self.K)
        v = d / self.C
        vref = dref / self.C
        if "detector_nonlinearity" in active:
            p = self.eff["detector_nonlinearity"]
            c2, c3 = p["scale"] * p["q2"], p["scale"] * p["q3"]
            v = v + c2 * v ** 2 + c3 * v ** 3
            vref = vref + c2 * vref ** 2 + c3 * vref ** 3
        sl = slice(None, None, self.os)
        out = dict(deflection_v=v[sl].copy(), reference_deflection_v=vref[sl].copy(),
                   height_nm=z_abs_nodelay[sl].copy(), contact=cont[sl].copy(), u_nN=u[sl].copy(),
                   zrel=zc[sl].copy())
        if "mains_interference" in active:
            p = self.eff["mains_interference"]
            m = np.zeros(self.N)
            mr = np.zeros(self.N)
            for k, (r, ph) in enumerate(zip(p["harm_rel"], p["phases_rad"])):
                m += r * np.sin(2 * np.pi * (k + 1) * p["f0_hz"] * self.t_out + ph)
                mr += r * np.sin(2 * np.pi * (k + 1) * p["f0_hz"] * self.t_out + ph + (k + 1) * self.phase_ref_mains)
            out["deflection_v"] += p["amp_v"] * m
            out["reference_deflection_v"] += p["amp_v"] * mr
        return out

    # -------------------------------------------------------------------------------
    def tune(self, targets, base_v, noise):
        """Scale each effect's strength so that rms(defl(effect) - defl(base)) = ratio * noise."""
        log = {}
        for e, ratio in targets.items():
            target = ratio * noise
            s = self.get_strength(e)
            hist = []
            for it in range(12):
                v = self.simulate([e])["deflection_v"]
                r = float(np.sqrt(np.mean((v - base_v) ** 2)))
                hist.append((s, r))
                s_used = s
                if abs(r / target - 1) < 0.02:
                    break
                if len(hist) >= 2 and hist[-1][1] > 0 and hist[-2][1] > 0 and hist[-1][0] != hist[-2][0]:
                    (s1, r1), (s2, r2) = hist[-2], hist[-1]
                    pexp = math.log(r2 / r1) / math.log(s2 / s1) if r2 != r1 else 1.0
                    pexp = min(max(pexp, 0.3), 3.0)
                else:
                    pexp = 1.0
                fac = (target / max(r, 1e-30)) ** (1.0 / pexp)
                fac = min(max(fac, 0.05), 20.0)
                s = s * fac
                s = self.clamp_strength(e, s)
                self.set_strength(e, s)
            self.set_strength(e, s_used)
            log[e] = dict(strength=float(s_used), effect_rms_v=r, target_rms_v=target, iters=len(hist))
        return log

    def clamp_strength(self, e, s):
        if e == "instrument_resonance":  # peak gain of the mode at most 1 + 4 (14 dB)
            return min(s, 4.0)
        if e == "channel_delay":
            return min(s, 6.0 / self.fs)
        if e == "tip_geometry" and self.tip == "sphere":
            return min(s, 0.9 * math.sqrt(self.R * self.h_op))
        if e == "tip_geometry":
            return min(s, 0.5)
        if e == "substrate_effect":  # keep chi = a_op / t <= 1 (validity of the polynomial)
            a_op = math.sqrt(self.R * self.h_op) if self.tip == "sphere" else \
                2 * self.h_op * math.tan(math.radians(self.alpha_deg)) / math.pi
            return min(s, 1.0 / a_op)
        return s


# ----------------------------------------------------------------------------------------
# Case table
# ----------------------------------------------------------------------------------------
def case_table():
    C = []

    def add(effects, **kw):
        d = dict(effects=effects, fs=8000, drive="v", ref=False, height=False, tip="sphere", exc="multisine")
        d.update(kw)
        C.append(d)

    add(["piezo_hysteresis"], fs=8000, drive="v", height=True, exc="multisine")
    add(["piezo_hysteresis"], fs=10000, drive="v", ref=True, exc="step")
    add(["piezo_creep"], fs=5000, drive="v", exc="step")
    add(["piezo_creep"], fs=10000, drive="v", height=True, exc="multisine")
    add(["thermal_drift"], fs=8000, drive="nm", ref=True, exc="multisine")
    add(["thermal_drift"], fs=5000, drive="v", exc="step")
    add(["missing_relaxation"], fs=8000, drive="v", ref=True, exc="step", mr_kind="slow")
    add(["missing_relaxation"], fs=20000, drive="nm", exc="multisine", mr_kind="mid")
    add(["instrument_resonance"], fs=10000, drive="v", exc="multisine")
    add(["instrument_resonance"], fs=16000, drive="nm", tip="cone", exc="step")
    add(["adhesion"], fs=8000, drive="v", exc="multisine", pink=0.5)
    add(["adhesion"], fs=10000, drive="nm", ref=True, tip="cone", exc="step")
    add(["tip_geometry"], fs=8000, drive="v", height=True, exc="multisine")
    add(["tip_geometry"], fs=10000, drive="nm", tip="cone", exc="multisine")
    add(["hydrodynamic_drag"], fs=10000, drive="v", exc="multisine")
    add(["hydrodynamic_drag"], fs=8000, drive="nm", ref=True, exc="multisine")
    add(["channel_delay"], fs=10000, drive="v", exc="multisine")
    add(["channel_delay"], fs=16000, drive="nm", height=True, exc="multisine")
    add(["mains_interference"], fs=5000, drive="v", exc="step", mains_f=50.0)
    add(["mains_interference"], fs=8000, drive="v", exc="multisine", mains_f=60.0, extra_col=True, pink=0.4)
    add(["detector_nonlinearity"], fs=10000, drive="v", exc="multisine", nu=0.45)
    add(["detector_nonlinearity"], fs=8000, drive="nm", tip="cone", exc="step")
    add(["substrate_effect"], fs=8000, drive="v", ref=True, exc="multisine")
    add(["substrate_effect"], fs=10000, drive="nm", tip="cone", exc="multisine", nu=0.4)
    # two-effect cases
    add(["thermal_drift", "adhesion"], fs=8000, drive="v", exc="step")
    add(["piezo_hysteresis", "mains_interference"], fs=10000, drive="v", height=True, exc="multisine", mains_f=50.0)
    add(["channel_delay", "missing_relaxation"], fs=20000, drive="nm", ref=True, exc="multisine", mr_kind="slow")
    add(["substrate_effect", "hydrodynamic_drag"], fs=8000, drive="v", exc="multisine")
    # null cases
    add([], fs=8000, drive="v", exc="multisine")
    add([], fs=10000, drive="nm", ref=True, tip="cone", exc="step")
    add([], fs=8000, drive="v", height=True, exc="multisine", pink=1.5)
    add([], fs=5000, drive="nm", ref=True, exc="step", pink=2.0)
    # SIM_CASES=controls (added by viscoprobe, not by the author): five recordings with the
    # drive in nm beside a height sensor, a make-up the set above has only with a delay.
    if os.environ.get("SIM_CASES") == "controls":
        C.clear()
        add([], fs=16000, drive="nm", height=True, exc="multisine")
        add([], fs=10000, drive="nm", height=True, exc="multisine")
        add(["tip_geometry"], fs=16000, drive="nm", height=True, exc="multisine")
        add(["missing_relaxation"], fs=16000, drive="nm", height=True, exc="multisine")
        add(["channel_delay"], fs=10000, drive="nm", height=True, exc="multisine")
    # SIM_CASES=refnulls (added by viscoprobe, not by the author): eight null recordings
    # beside a hard reference, a make-up the set above has twice: a false-positive control
    # for what the diagnosis credits to the reference channel.
    if os.environ.get("SIM_CASES") == "refnulls":
        C.clear()
        add([], fs=8000, drive="v", ref=True, exc="step")
        add([], fs=10000, drive="v", ref=True, exc="multisine")
        add([], fs=5000, drive="v", ref=True, tip="cone", exc="step")
        add([], fs=16000, drive="nm", ref=True, exc="multisine")
        add([], fs=8000, drive="nm", ref=True, exc="step", pink=1.0)
        add([], fs=20000, drive="v", ref=True, exc="multisine")
        add([], fs=10000, drive="v", ref=True, tip="cone", exc="step")
        add([], fs=8000, drive="v", ref=True, exc="multisine", pink=0.5)
    # SIM_CASES=slow (added by viscoprobe, not by the author): eight slow effects (drift,
    # creep, a slow fourth retardation time) under 1/f noise at 1-3 times the white level
    # (x 0.8-1.5 as drawn): what the false-positive guard against 1/f noise costs.
    if os.environ.get("SIM_CASES") == "slow":
        C.clear()
        add(["thermal_drift"], fs=8000, drive="v", exc="multisine", pink=1.0)
        add(["thermal_drift"], fs=20000, drive="v", exc="step", pink=2.0)
        add(["thermal_drift"], fs=5000, drive="nm", exc="step", pink=1.0)
        add(["piezo_creep"], fs=10000, drive="v", exc="multisine", pink=2.0)
        add(["piezo_creep"], fs=20000, drive="v", exc="step", pink=1.0)
        add(["missing_relaxation"], fs=8000, drive="v", exc="step", mr_kind="slow", pink=2.0)
        add(["thermal_drift"], fs=10000, drive="v", exc="step", pink=3.0)
        add(["missing_relaxation"], fs=20000, drive="nm", exc="multisine", mr_kind="slow", pink=1.0)
    # SIM_CASES=nulls (added by viscoprobe, not by the author): sixteen nulls over the make-ups
    # of the default set, half of them with 1/f noise up to 3× the white noise (the default
    # set's nulls go to 2×): a false-positive control beyond the default set's four nulls.
    # SIM_CASES=fast (added by viscoprobe, not by the author): ten recordings at 50 and
    # 100 kHz (20 000 samples, 0.4 and 0.2 s), beyond the default set's 5-20 kHz.
    if os.environ.get("SIM_CASES") == "fast":
        C.clear()
        add([], fs=50000, drive="v", exc="multisine")
        add([], fs=50000, drive="nm", exc="step")
        add(["adhesion"], fs=50000, drive="v", exc="step")
        add(["hydrodynamic_drag"], fs=50000, drive="nm", exc="multisine")
        add(["instrument_resonance"], fs=50000, drive="v", exc="multisine")
        add(["channel_delay"], fs=50000, drive="v", exc="multisine")
        add(["mains_interference"], fs=50000, drive="v", exc="step")
        add(["piezo_hysteresis"], fs=50000, drive="v", exc="multisine")
        add([], fs=100000, drive="v", exc="multisine")
        add(["adhesion"], fs=100000, drive="nm", exc="step")
    if os.environ.get("SIM_CASES") == "nulls":
        C.clear()
        for k, (fs, drive, tip, exc) in enumerate([
            (5000, "v", "sphere", "multisine"), (8000, "nm", "sphere", "step"),
            (10000, "v", "cone", "multisine"), (16000, "nm", "cone", "multisine"),
            (20000, "v", "sphere", "step"), (8000, "v", "cone", "step"),
            (10000, "nm", "sphere", "multisine"), (5000, "nm", "cone", "step"),
        ]):
            for pink in (0.0, (1.0, 2.0, 3.0)[k % 3]):
                kw = dict(fs=fs, drive=drive, tip=tip, exc=exc)
                if pink:
                    kw["pink"] = pink
                if k % 4 == 1:
                    kw["ref"] = True
                if k % 4 == 3:
                    kw["height"] = True
                add([], **kw)
    return C


def build_case(idx, spec):
    seed = SEED + 1000 * idx
    rec = Recording(spec, seed)
    rng = np.random.default_rng(seed + 7)
    base = rec.simulate([])
    v0 = base["deflection_v"]
    exc = (rec.t_out > rec.proto.t3) & (rec.t_out < rec.proto.t4)
    noise = rec.noise_nm / rec.C
    targets = {}
    for e in spec["effects"]:
        lo, hi = (2.0, 4.0) if e in ("missing_relaxation", "tip_geometry", "substrate_effect") else (1.5, 3.5)
        if len(spec["effects"]) > 1:
            hi = min(hi, 3.0)
        # SIM_RATIO_SCALE (added by viscoprobe, not by the author): every drawn multiple
        # times this factor, for effects beyond the near-floor sizes the set was made for.
        targets[e] = float(rng.uniform(lo, hi)) * float(os.environ.get("SIM_RATIO_SCALE", "1"))
    tune_log = rec.tune(targets, v0, noise) if targets else {}
    full = rec.simulate(spec["effects"])
    return rec, base, full, noise, tune_log, targets


def fmt(x, f="%.7g"):
    return [f % v for v in x]


def write_case(outdir, name, idx, spec, rec, base, full, noise, tune_log, targets):
    rng = np.random.default_rng(rec.noise_seed)
    N = rec.N
    t = rec.t_out
    white = rng.standard_normal(N) * noise
    pink_rms = rec.pink_ratio * noise
    pink = pink_noise(rng, N, pink_rms) if pink_rms > 0 else np.zeros(N)
    defl = full["deflection_v"] + white + pink
    cols = {}
    cols["time_s"] = ["%.9f" % x for x in t]
    drive_abs = rec.zcmd_abs(t)
    if rec.drive_kind == "v":
        cols["drive_v"] = fmt(drive_abs / rec.gain, "%.8g")
    else:
        cols["drive_nm"] = fmt(drive_abs, "%.8g")
    cols["deflection_v"] = fmt(defl)
    if spec["ref"]:
        rw = rng.standard_normal(N) * noise
        rp = pink_noise(rng, N, pink_rms) if pink_rms > 0 else np.zeros(N)
        cols["reference_deflection_v"] = fmt(full["reference_deflection_v"] + rw + rp)
    if spec["height"]:
        cols["measured_height_nm"] = fmt(full["height_nm"] + rng.standard_normal(N) * rec.sig_h, "%.8g")
    if spec.get("extra_col"):
        cols["lateral_v"] = fmt(0.02 + 0.003 * rng.standard_normal(N) + 0.01 * full["contact"])
    names = list(cols.keys())
    if idx % 3 == 1:  # vary column order a little
        names = [names[0]] + names[2:3] + names[1:2] + names[3:]
    with open(os.path.join(outdir, "recs", name + ".csv"), "w", newline="") as f:
        f.write(",".join(names) + "\n")
        rows = zip(*[cols[n] for n in names])
        f.write("\n".join(",".join(r) for r in rows) + "\n")
    # sidecar
    samples = {"sphere": "agarose gel", "cone": "PDMS"}
    sname = ["PDMS", "polyacrylamide gel", "agarose gel", "PVA hydrogel", "soft PU", "gelatin"][idx % 6]
    lines = ['format = "recording/1"', "sample_rate_hz = %.1f" % rec.fs, "",
             "[cantilever]", "spring_constant_n_per_m = %.6g" % rec.K,
             "deflection_sensitivity_nm_per_v = %.6g" % rec.C, "", "[tip]", 'shape = "%s"' % rec.tip]
    if rec.tip == "sphere":
        lines.append("radius_nm = %.6g" % rec.R)
    else:
        lines.append("half_angle_deg = %.6g" % rec.alpha_deg)
    lines += ["", "[piezo]", "gain_nm_per_v = %.6g" % rec.gain, "", "[sample]", 'name = "%s"' % sname,
              "poisson_ratio = %.3g" % rec.nu, "", "[notes]", 'operator = "thirdparty2 simulator"',
              'run = "%s"' % name, ""]
    with open(os.path.join(outdir, "recs", name + ".toml"), "w") as f:
        f.write("\n".join(lines))
    # clean
    with open(os.path.join(outdir, "clean", name + "_clean.csv"), "w") as f:
        f.write("time_s,deflection_v\n")
        f.write("\n".join("%.9f,%.9g" % (a, b) for a, b in zip(t, full["deflection_v"])) + "\n")
    with open(os.path.join(outdir, "clean", name + "_noeffect.csv"), "w") as f:
        f.write("time_s,deflection_v\n")
        f.write("\n".join("%.9f,%.9g" % (a, b) for a, b in zip(t, base["deflection_v"])) + "\n")
    eff_rms = float(np.sqrt(np.mean((full["deflection_v"] - base["deflection_v"]) ** 2)))
    # phases for validation
    pr = rec.proto
    cont = full["contact"]
    first_contact = float(t[np.argmax(cont)]) if cont.any() else None
    retract = (t >= pr.t4)
    lost = np.where(retract & ~cont)[0]
    pulloff_t = float(t[lost[0]]) if len(lost) else None
    exc = (t > pr.t3) & (t < pr.t4)
    truth = dict(
        name=name, effects=list(spec["effects"]),
        params={e: rec.eff[e] for e in spec["effects"]},
        noise_rms_v=noise, pink_noise_rms_v=pink_rms, noise_rms_nm=noise * rec.C,
        snr_excitation=float(np.std(base["deflection_v"][exc]) / noise), effect_rms_v=eff_rms,
        ratio=eff_rms / noise,
        per_effect=tune_log,
        nominal=dict(
            sample_rate_hz=rec.fs, n_samples=N, spring_constant_n_per_m=rec.K,
            deflection_sensitivity_nm_per_v=rec.C, tip=rec.tip,
            radius_nm=getattr(rec, "R", None), half_angle_deg=getattr(rec, "alpha_deg", None),
            poisson_ratio=rec.nu, gain_nm_per_v=rec.gain, drive=("drive_v" if rec.drive_kind == "v" else "drive_nm"),
            surface_command_nm=rec.z_surf,
            actuator=(dict(type="2nd_order", f_hz=rec.act_f, zeta=rec.act_zeta) if rec.drive_kind == "v"
                      else dict(type="1st_order_lag", f_c_hz=rec.act_f)),
            prony=dict(convention="J(t)=J0+sum Ji(1-exp(-t/tau_i)), 1/Pa", J0=rec.J0, Ji=rec.Ji, tau_s=rec.taus),
            h_op_nm=rec.h_op, protocol=pr.params, height_sensor_noise_nm=(rec.sig_h if spec["height"] else None),
            columns=names),
        checks=dict(first_contact_s=first_contact, contact_at_first_sample=bool(cont[0]),
                    contact_lost_during_excitation=bool((~cont[exc]).any()), pulloff_s=pulloff_t,
                    min_clean_retract_v=float(np.min(full["deflection_v"][retract]))),
        notes=notes_for(spec, rec),
    )
    return truth


def notes_for(spec, rec):
    n = []
    n.append("%s tip, %s, %s excitation, fs=%g Hz" % (rec.tip, "drive_v" if rec.drive_kind == "v" else "drive_nm",
                                                     spec["exc"], rec.fs))
    if spec["ref"]:
        n.append("reference_deflection_v: same actuator/detector chain on a rigid sample, own noise")
    if spec["height"]:
        n.append("measured_height_nm: true actuator position (incl. piezo effects, not thermal drift) + sensor noise")
    if spec.get("extra_col"):
        n.append("extra column lateral_v (unknown to the format)")
    if spec.get("pink"):
        n.append("1/f noise present on deflection channel(s)")
    if not spec["effects"]:
        n.append("null case")
    return "; ".join(n)


def run_one(args):
    outdir, idx, name, spec = args
    rec, base, full, noise, tune_log, targets = build_case(idx, spec)
    tr = write_case(outdir, name, idx, spec, rec, base, full, noise, tune_log, targets)
    print("%s %-45s ratio=%.2f" % (name, "+".join(spec["effects"]) or "(none)", tr["ratio"]), flush=True)
    return tr


def main():
    outdir = sys.argv[1] if len(sys.argv) > 1 else os.path.dirname(os.path.abspath(__file__))
    only = sys.argv[2:] if len(sys.argv) > 2 else None
    os.makedirs(os.path.join(outdir, "recs"), exist_ok=True)
    os.makedirs(os.path.join(outdir, "clean"), exist_ok=True)
    cases = case_table()
    perm = np.random.default_rng(SEED).permutation(len(cases))
    jobs = []
    for k, ci in enumerate(perm):
        name = "rec%02d" % (k + 1)
        if only and name not in only:
            continue
        jobs.append((outdir, int(ci), name, cases[ci]))
    nproc = int(os.environ.get("SIM_PROCS", os.cpu_count() or 1))
    if nproc > 1:
        import multiprocessing as mp
        with mp.Pool(nproc) as pool:
            truths = pool.map(run_one, jobs, chunksize=1)
    else:
        truths = [run_one(j) for j in jobs]
    truths.sort(key=lambda d: d["name"])
    tp = os.path.join(outdir, "truth.json")
    if only and os.path.exists(tp):
        old = {d["name"]: d for d in json.load(open(tp))}
        for d in truths:
            old[d["name"]] = d
        truths = [old[k] for k in sorted(old)]
    with open(tp, "w") as f:
        json.dump(truths, f, indent=1, default=float)


if __name__ == "__main__":
    main()
