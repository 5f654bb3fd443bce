#!/usr/bin/env python3
"""Blind simulator #4 of AFM/SPM indentation recordings (recording/1 format).

Written without reading the project's code.  Usage:  python3 sim.py OUTDIR
Writes OUTDIR/recs/recNN.csv + recNN.toml and OUTDIR/truth.json.
numpy + scipy only.  Deterministic (SEED; one sub-stream per record and attempt).
"""
import sys, os, json, math, time, bisect
import numpy as np
from scipy import signal

SEED = 20261206
VFS = 10.0                 # ADC / photodiode full scale, V
N_RECORDS = 46

IDS = ['piezo_hysteresis', 'piezo_creep', 'thermal_drift', 'missing_relaxation',
       'instrument_resonance', 'adhesion', 'tip_geometry', 'hydrodynamic_drag',
       'channel_delay', 'mains_interference', 'detector_nonlinearity', 'substrate_effect']


class Fail(Exception):
    pass


def logu(rng, a, b):
    return float(math.exp(rng.uniform(math.log(a), math.log(b))))


# ----------------------------------------------------------------------------------------------
# Contact geometry: Phi(h) = P/E (nm^2), tabulated on a log grid, log-log interpolation.
# Viscoelastic (Lee-Radok):  Phi(h(t)) = int J(t - s) dP(s).
# ----------------------------------------------------------------------------------------------
class Phi:
    def __init__(self, h, phi):
        h = np.asarray(h, float); phi = np.asarray(phi, float)
        ok = (h > 0) & (phi > 0) & np.isfinite(h) & np.isfinite(phi)
        h, phi = h[ok], phi[ok]
        o = np.argsort(h); h, phi = h[o], phi[o]
        keep = np.concatenate([[True], (np.diff(np.log(h)) > 1e-9) & (np.diff(np.log(phi)) > 1e-12)])
        h, phi = h[keep], phi[keep]
        self.LH = [float(v) for v in np.log(h)]
        self.LP = [float(v) for v in np.log(phi)]
        s = np.diff(np.log(phi)) / np.diff(np.log(h))
        self.S = [float(s[0])] + [float(v) for v in s] + [float(s[-1])]
        self.n = len(self.LH)

    def vd(self, h):
        """value and derivative at h > 0"""
        lh = math.log(h)
        i = bisect.bisect_left(self.LH, lh)
        s = self.S[i]
        if i == 0:
            lp = self.LP[0] + s * (lh - self.LH[0])
        else:
            lp = self.LP[i - 1] + s * (lh - self.LH[i - 1])
        p = math.exp(lp)
        return p, s * p / h

    def val(self, h):
        return self.vd(h)[0]

    def inv(self, y):
        ly = math.log(y)
        i = bisect.bisect_left(self.LP, ly)
        s = self.S[i]
        if i == 0:
            lh = self.LH[0] + (ly - self.LP[0]) / s
        else:
            lh = self.LH[i - 1] + (ly - self.LP[i - 1]) / s
        return math.exp(lh)


HGRID = np.geomspace(1e-4, 3e5, 700)


def phi_declared(tip, nu):
    es = 1.0 / (1.0 - nu * nu)
    if tip['shape'] == 'sphere':
        c = (4.0 / 3.0) * es * math.sqrt(tip['radius_nm'])
        return Phi(HGRID, c * HGRID ** 1.5)
    c = (2.0 / math.pi) * es * math.tan(math.radians(tip['half_angle_deg']))
    return Phi(HGRID, c * HGRID ** 2)


def phi_sneddon(fprime, a_grid, nu):
    """Sneddon for an axisymmetric rigid punch with slope f'(r):
    h(a) = a int_0^{pi/2} f'(a sin t) dt ;  P/E = 2/(1-nu^2) a^2 int_0^{pi/2} sin^2 t f'(a sin t) dt"""
    nt = 3000
    th = (np.arange(nt) + 0.5) * (math.pi / 2) / nt
    dth = (math.pi / 2) / nt
    st = np.sin(th)
    hs, ps = [], []
    for a in a_grid:
        fp = fprime(a * st)
        hs.append(a * np.sum(fp) * dth)
        ps.append(2.0 / (1 - nu * nu) * a * a * np.sum(st * st * fp) * dth)
    return np.array(hs), np.array(ps)


def phi_powerlaw(n, B, nu):
    # profile z = B r^n  (Galin):  h = k_n B a^n,  P/E = 2/(1-nu^2) n/(n+1) k_n B a^{n+1}
    from scipy.special import gamma
    kn = math.sqrt(math.pi) * gamma(n / 2 + 1) / gamma((n + 1) / 2)
    a = (HGRID / (kn * B)) ** (1.0 / n)
    return Phi(HGRID, 2.0 / (1 - nu * nu) * n / (n + 1) * kn * B * a ** (n + 1))


# ----------------------------------------------------------------------------------------------
# Material: J(t) = J0 - sum Ji exp(-t/tau_i)   (J in 1/Pa, tau in s)
# ----------------------------------------------------------------------------------------------
def mat_scale(mat, k):
    return {'J0': mat['J0'] * k, 'J': [j * k for j in mat['J']], 'tau': list(mat['tau'])}


def mat_J(mat, t):
    t = np.asarray(t, float)
    out = np.full_like(t, mat['J0'])
    for j, tau in zip(mat['J'], mat['tau']):
        out -= j * np.exp(-t / tau)
    return out


class Solver:
    """Per-sample quasi-static solution of cantilever + viscoelastic contact.
    Kt*d = P + Fext ;  h = delta - d ;  Phi(h) = A*P + B  (exact integration of the Prony
    kernel for piecewise-linear P).  Adhesion: DMT force Fad in contact, capillary-like neck
    F = Fad (1 - g/L) after separation, broken at g = L."""

    def __init__(self, mat, phi, Kt, T, Fad=0.0, Lneck=1.0):
        self.phi = phi; self.Kt = Kt
        J = [j * 1e9 for j in mat['J']]           # nm^2 / nN
        self.e = [math.exp(-T / tau) for tau in mat['tau']]
        self.g = [tau / T * (1 - e) for tau, e in zip(mat['tau'], self.e)]
        self.Jn = J
        self.A = mat['J0'] * 1e9 - sum(j * g for j, g in zip(J, self.g))
        self.x = [0.0] * len(J)
        self.k = len(J)
        self.Pp = 0.0; self.hp = 1.0
        self.contact = False; self.neck = False
        self.Fad = Fad; self.L = Lneck; self.kn = Fad / Lneck if Fad > 0 else 0.0
        self.gap = 1e9

    def step(self, delta, fdrag):
        Jn, e, g, x = self.Jn, self.e, self.g, self.x
        B = 0.0
        for i in range(self.k):
            B += Jn[i] * (g[i] * self.Pp - e[i] * x[i])
        Kt = self.Kt
        adh = self.Fad > 0 and (self.contact or self.neck)
        Fext = fdrag - (self.Fad if adh else 0.0)
        htf = delta - Fext / Kt
        contact = False
        if htf > 0.0:
            if self.phi.val(htf) > B:
                contact = True
        if contact:
            A = self.A; AK = A * Kt
            C = A * (Kt * delta - Fext) + B
            lo, hi = 0.0, htf
            h = self.hp
            if not (lo < h < hi):
                h = 0.5 * (lo + hi)
            phi = self.phi
            for _ in range(60):
                p, dp = phi.vd(h)
                q = p + AK * h - C
                if q > 0:
                    hi = h
                else:
                    lo = h
                hn = h - q / (dp + AK)
                if not (lo < hn < hi):
                    hn = 0.5 * (lo + hi)
                if abs(hn - h) <= 1e-11 * (h + 1e-6):
                    h = hn
                    break
                h = hn
            P = Kt * (delta - h) - Fext
            if P <= 0.0:
                contact = False
        if contact:
            d = delta - h
            self.hp = h
            if self.Fad > 0:
                self.neck = True
            self.gap = 0.0
        else:
            P = 0.0
            hs = self.phi.inv(B) if B > 1e-300 else 0.0
            if self.neck:
                d = (-self.Fad + self.kn * (hs - delta) + fdrag) / (Kt - self.kn)
                gg = hs - (delta - d)
                if gg > self.L:
                    self.neck = False
                    d = fdrag / Kt
            else:
                d = fdrag / Kt
            h = delta - d
            self.gap = max(hs - h, 0.0)
        dP = P - self.Pp
        for i in range(self.k):
            x[i] = e[i] * x[i] + g[i] * dP
        self.Pp = P
        self.contact = contact
        return d, P, h, contact


# ----------------------------------------------------------------------------------------------
# Actuator chain pieces
# ----------------------------------------------------------------------------------------------
def tf_zoh(num, den, T):
    b, a, _ = signal.cont2discrete((num, den), T, method='zoh')
    b = np.atleast_1d(np.squeeze(b)); a = np.atleast_1d(a)
    return b / a[0], a / a[0]


def filt(b, a, x):
    zi = signal.lfilter_zi(b, a) * x[0]
    y, _ = signal.lfilter(b, a, x, zi=zi)
    return y


class IIRstep:
    def __init__(self, b, a, x0):
        self.b = [float(v) for v in b]; self.a = [float(v) for v in a]
        n = max(len(self.b), len(self.a))
        self.b += [0.0] * (n - len(self.b)); self.a += [0.0] * (n - len(self.a))
        self.z = [float(v) for v in signal.lfilter_zi(b, a) * x0] + [0.0]
        self.n = n

    def step(self, x):
        b, a, z = self.b, self.a, self.z
        y = b[0] * x + z[0]
        for i in range(1, self.n):
            z[i - 1] = b[i] * x + z[i] - a[i] * y
        return y


def nominal_act_tf(rec):
    w = 2 * math.pi * rec['act_fn']; z = rec['act_zeta']
    return tf_zoh([w * w], [1, 2 * z * w, w * w], rec['T'])


def stage_tf(p, T):
    w = 2 * math.pi * p['f_hz']; Q = p['Q']; a = p['a']
    return tf_zoh([(1 - a), (1 - a) * w / Q, w * w], [1, w / Q, w * w], T)


def holder_tf(p, T):
    w = 2 * math.pi * p['f_hz']; Q = p['Q']
    return tf_zoh([-p['a'], 0, 0], [1, w / Q, w * w], T)


def creep_taus(rec):
    tmin = max(20 * rec['T'], 1e-3)
    tmax = 10 * rec['dur']
    out = []
    t = tmin
    while t <= tmax:
        out.append(t); t *= 10
    return out


def hysteresis(x, p):
    r = p['thresholds_nm']; w = p['weights']; W = sum(w)
    y = [x[0] + ri for ri in r]
    out = np.empty_like(x)
    k = len(r)
    x0 = x[0]
    xl = x.tolist()
    for n in range(len(xl)):
        xn = xl[n]
        s = (1 - W) * xn
        for i in range(k):
            yi = y[i]
            lo = xn - r[i]; hi = xn + r[i]
            if yi < lo:
                yi = lo
            elif yi > hi:
                yi = hi
            y[i] = yi
            s += w[i] * (yi - r[i])
        out[n] = s
    return out


def creep_vec(x, p, rec):
    taus = creep_taus(rec); gam = p['gamma_per_decade']
    acc = x.copy()
    for tau in taus:
        e = math.exp(-rec['T'] / tau)
        acc = acc + gam * filt(np.array([1 - e]), np.array([1.0, -e]), x)
    return acc / (1 + gam * len(taus))


def actuator(rec, eff, xcmd):
    x = xcmd
    if 'piezo_hysteresis' in eff:
        x = hysteresis(x, eff['piezo_hysteresis'])
    if 'piezo_creep' in eff:
        x = creep_vec(x, eff['piezo_creep'], rec)
    b, a = nominal_act_tf(rec)
    z = filt(b, a, x)
    ir = eff.get('instrument_resonance')
    if ir and ir['kind'] == 'stage':
        b, a = stage_tf(ir, rec['T'])
        z = filt(b, a, z)
    return z


class ActStep:
    """sample-by-sample version of actuator() (used inside the force feedback loop)"""

    def __init__(self, rec, eff, x0):
        self.rec = rec; self.eff = eff
        self.h = eff.get('piezo_hysteresis')
        if self.h:
            self.hy = [x0 + r for r in self.h['thresholds_nm']]
        self.c = eff.get('piezo_creep')
        if self.c:
            self.taus = creep_taus(rec)
            self.ce = [math.exp(-rec['T'] / t) for t in self.taus]
            self.cy = [x0] * len(self.taus)
        b, a = nominal_act_tf(rec)
        self.f1 = IIRstep(b, a, x0)
        ir = eff.get('instrument_resonance')
        self.f2 = None
        if ir and ir['kind'] == 'stage':
            b, a = stage_tf(ir, rec['T'])
            self.f2 = IIRstep(b, a, x0)

    def step(self, x):
        if self.h:
            r = self.h['thresholds_nm']; w = self.h['weights']; W = sum(w)
            s = (1 - W) * x
            for i in range(len(r)):
                self.hy[i] = min(max(self.hy[i], x - r[i]), x + r[i])
                s += w[i] * (self.hy[i] - r[i])
            x = s
        if self.c:
            g = self.c['gamma_per_decade']
            acc = x
            for i, e in enumerate(self.ce):
                self.cy[i] = e * self.cy[i] + (1 - e) * x
                acc += g * self.cy[i]
            x = acc / (1 + g * len(self.taus))
        z = self.f1.step(x)
        if self.f2:
            z = self.f2.step(z)
        return z


# ----------------------------------------------------------------------------------------------
# Measurement-chain pieces
# ----------------------------------------------------------------------------------------------
def drift_defl(rec, p, t):
    if p is None or p['mode'] == 'sample':
        return 0.0 * t
    k = p['scale']
    D = rec['dur']
    return k * (p['defl_rate_v_per_s'] * t + p['defl_curv_v_per_s'] * t * t / D
                + p['defl_settle_v'] * (1 - np.exp(-t / p['defl_settle_tau_s'])))


def drift_sample(rec, p, t):
    if p is None or p['mode'] == 'deflection':
        return 0.0 * t
    k = p['scale']
    D = rec['dur']
    return k * (p['sample_rate_nm_per_s'] * t + p['sample_curv_nm_per_s'] * t * t / D)


def nl_map(v, p):
    if p['kind'] == 'poly':
        return v + p['a2'] * v * v / VFS + p['a3'] * v ** 3 / VFS ** 2
    vs = 1.0 / p['inv_vsat']
    return vs * np.tanh(v / vs)


def frac_delay(x, D):
    N = len(x)
    idx = np.arange(N) - D
    i0 = np.floor(idx).astype(int)
    mu = idx - i0
    out = np.zeros(N)
    # cubic Lagrange on nodes i0-1, i0, i0+1, i0+2
    nodes = [-1, 0, 1, 2]
    for k in nodes:
        wk = np.ones(N)
        for m in nodes:
            if m != k:
                wk *= (mu - m) / (k - m)
        out += wk * x[np.clip(i0 + k, 0, N - 1)]
    return out


def mains(rec, p, t):
    s = np.zeros_like(t)
    for k, (amp, ph) in enumerate(zip(p['harmonic_rel'], p['phases_rad'])):
        f = (k + 1) * p['f_hz']
        if f < 0.45 * rec['fs']:
            s += p['amp_v'] * amp * np.sin(2 * math.pi * f * t + ph)
    return s


# ----------------------------------------------------------------------------------------------
# Full forward model for a given drive
# ----------------------------------------------------------------------------------------------
def simulate(rec, xcmd, eff, mat, phi):
    """xcmd: commanded actuator displacement, nm (absolute frame).  Returns noise-free channels."""
    T = rec['T']; N = len(xcmd); t = np.arange(N) * T
    z = actuator(rec, eff, xcmd)
    zs = rec['zs_abs'] + drift_sample(rec, eff.get('thermal_drift'), t)
    delta = z - zs
    vel = np.gradient(z, T)
    adh = eff.get('adhesion')
    sol = Solver(mat, phi, rec['Kt'], T, adh['F_ad_nN'] if adh else 0.0, adh['neck_length_nm'] if adh else 1.0)
    dr = eff.get('hydrodynamic_drag')
    d = np.empty(N); P = np.empty(N); h = np.empty(N); c = np.zeros(N, bool)
    dl = delta.tolist(); vl = vel.tolist()
    if dr:
        binf = dr['beta_inf_Nspm']; b0 = dr['beta_near_Nspm']; H = dr['tip_height_nm']
    for n in range(N):
        fd = 0.0
        if dr:
            fd = (binf + b0 * H / (sol.gap + H)) * vl[n]
        d[n], P[n], h[n], c[n] = sol.step(dl[n], fd)
    out = {'z': z, 'd': d, 'P': P, 'h': h, 'contact': c}
    dm = d.copy()
    ir = eff.get('instrument_resonance')
    hold = None
    if ir and ir['kind'] == 'holder':
        b, a = holder_tf(ir, T)
        hold = filt(b, a, z)
        dm = dm + hold
    v0 = rec['v0']; Ct = rec['Ct']
    V = v0 + dm / Ct + drift_defl(rec, eff.get('thermal_drift'), t)
    nl = eff.get('detector_nonlinearity')
    if nl:
        V = nl_map(V, nl) - nl_map(np.array([v0]), nl)[0] + v0
    if 'mains_interference' in eff:
        V = V + mains(rec, eff['mains_interference'], t + rec['t0'])
    if 'channel_delay' in eff:
        V = frac_delay(V, eff['channel_delay']['delay_samples'])
    out['V'] = V
    dh = np.maximum(z - rec['zs_abs'], 0.0)
    if hold is not None:
        dh = dh + hold
    Vr = v0 + dh / Ct
    if nl:
        Vr = nl_map(Vr, nl) - nl_map(np.array([v0]), nl)[0] + v0
    out['Vref'] = Vr
    return out


# ----------------------------------------------------------------------------------------------
# Protocols -> commanded displacement (nm, absolute frame)
# ----------------------------------------------------------------------------------------------
def taper(n, frac):
    w = np.ones(n)
    m = max(2, int(frac * n))
    r = 0.5 - 0.5 * np.cos(np.linspace(0, math.pi, m))
    w[:m] = r; w[-m:] = r[::-1]
    return w


def build_open_loop(rec, rng):
    p = rec['protocol']; N = rec['N']; T = rec['T']
    n_pre, n_a, n_r = rec['n_pre'], rec['n_a'], rec['n_r']
    n_e = N - n_pre - n_a - n_r - rec['n_post']
    g0 = rec['g0']; dop = rec['delta_op']
    te = np.arange(n_e) * T; Te = n_e * T
    kind = p['kind']
    if kind == 'height_step':
        d1 = p['d1_frac'] * dop
        ns = int(p['step_at_frac'] * n_e)
        ex = np.full(n_e, dop); ex[:ns] = d1
        nr = max(1, p['rise_samples'])
        ex[ns:ns + nr] = d1 + (dop - d1) * (np.arange(1, nr + 1) / nr)[:len(ex[ns:ns + nr])]
    elif kind == 'triangle':
        A = p['amp_frac'] * dop; nc = p['cycles']
        ph = (te / Te * nc) % 1.0
        tri = np.where(ph < 0.5, 2 * ph, 2 - 2 * ph)
        ex = dop - A + 2 * A * tri
    elif kind == 'staircase':
        A = p['amp_frac'] * dop; m = p['steps']
        levels = np.linspace(dop - A, dop + A, m)
        if p['updown']:
            levels = np.concatenate([levels, levels[-2::-1]])
        seg = np.minimum((te / Te * len(levels)).astype(int), len(levels) - 1)
        ex = levels[seg]
    elif kind == 'multisine':
        A = p['amp_frac'] * dop
        fr = np.array(p['freqs_hz']); ph = np.array(p['phases_rad'])
        s = np.zeros(n_e)
        for f, q in zip(fr, ph):
            s += np.sin(2 * math.pi * f * te + q)
        s /= np.max(np.abs(s))
        ex = dop + A * s * taper(n_e, 0.05)
    elif kind == 'chirp':
        A = p['amp_frac'] * dop
        f0, f1 = p['f0_hz'], p['f1_hz']
        k = math.log(f1 / f0) / Te
        phase = 2 * math.pi * f0 * (np.exp(k * te) - 1) / k
        ex = dop + A * np.sin(phase) * taper(n_e, 0.04)
    elif kind == 'sines':
        A = p['amp_frac'] * dop
        fr = p['freqs_hz']; m = len(fr)
        ex = np.full(n_e, dop)
        nb = n_e // m
        for i, f in enumerate(fr):
            a0 = i * nb; a1 = n_e if i == m - 1 else (i + 1) * nb
            tb = np.arange(a1 - a0) * T
            ex[a0:a1] = dop + A * np.sin(2 * math.pi * f * tb) * taper(a1 - a0, 0.1)
    else:
        raise ValueError(kind)
    b_end_final = -rec['retract_extra']
    app = np.linspace(0, g0 + ex[0], n_a + 1)[1:]
    ret = np.linspace(g0 + ex[-1], b_end_final, n_r + 1)[1:]
    b = np.concatenate([np.zeros(n_pre), app, g0 + ex, ret, np.full(rec['n_post'], b_end_final)])
    return rec['x_off'] + b


def build_feedback(rec, eff, mat, phi):
    """force clamp: open-loop approach until the deflection reaches setpoint 1, integral
    feedback on the deflection (setpoint 1, then step to setpoint 2), open-loop retract."""
    p = rec['protocol']; N = rec['N']; T = rec['T']
    t = np.arange(N) * T
    x0 = rec['x_off']
    act = ActStep(rec, eff, x0)
    adh = eff.get('adhesion')
    sol = Solver(mat, phi, rec['Kt'], T, adh['F_ad_nN'] if adh else 0.0, adh['neck_length_nm'] if adh else 1.0)
    dr = eff.get('hydrodynamic_drag')
    ddrift = drift_defl(rec, eff.get('thermal_drift'), t) * rec['Ct']    # nm equivalent
    sdrift = drift_sample(rec, eff.get('thermal_drift'), t)
    n_start = rec['n_pre']; n_ret = N - rec['n_r'] - rec['n_post']
    v_app = p['v_app_nm_per_s']; ki = p['ki_per_s']
    sp1, sp2 = p['sp1_nm'], p['sp2_nm']
    n_step = None
    x = x0; zprev = x0
    nl = eff.get('detector_nonlinearity'); v0 = rec['v0']; Ct = rec['Ct']
    nlv0 = float(nl_map(v0, nl)) if nl else 0.0
    xs = np.empty(N)
    state = 'pre'; meas = 0.0; x_ret = None; v_ret = None
    for n in range(N):
        if state == 'pre':
            if n >= n_start:
                state = 'app'
        if state == 'app':
            x += v_app * T
            if meas >= sp1:
                state = 'hold'; n_step = n + p['hold1_samples']
        elif state == 'hold':
            sp = sp1 if n < n_step else sp2
            x += ki * T * (sp - meas)
            if n >= n_ret:
                state = 'ret'; x_ret = x
                v_ret = (x - (x0 - rec['retract_extra'])) / (rec['n_r'] * T)
        elif state == 'ret':
            x -= v_ret * T
            if x <= x0 - rec['retract_extra']:
                x = x0 - rec['retract_extra']; state = 'post'
        xs[n] = x
        z = act.step(x)
        fd = 0.0
        if dr:
            fd = (dr['beta_inf_Nspm'] + dr['beta_near_Nspm'] * dr['tip_height_nm'] /
                  (sol.gap + dr['tip_height_nm'])) * (z - zprev) / T
        zprev = z
        d, P, h, c = sol.step(z - rec['zs_abs'] - sdrift[n], fd)
        meas = d + ddrift[n]
        if nl:   # the controller reads the same (nonlinear) photodiode signal
            meas = (nl_map(v0 + meas / Ct, nl) - nlv0) * Ct
    if state in ('pre', 'app'):
        raise Fail('feedback never triggered')
    if state == 'hold':
        raise Fail('feedback never retracted')
    return xs


def make_drive(rec, eff, mat, phi, rng=None):
    if rec['protocol']['kind'] == 'force_clamp':
        x = build_feedback(rec, eff, mat, phi)
    else:
        x = build_open_loop(rec, rng)
    # quantise / round exactly as written into the CSV
    if rec['drive_col'] == 'drive_v':
        v = x / rec['gain']
        if rec['dac_bits']:
            lsb = 2 * VFS / 2 ** rec['dac_bits']
            v = np.round(v / lsb) * lsb
        v = np.array([float('%.9g' % q) for q in v])
        return v, v * rec['gain']
    x = np.array([float('%.9g' % q) for q in x])
    return x, x


# ----------------------------------------------------------------------------------------------
# Random record (nominal part)
# ----------------------------------------------------------------------------------------------
PROTOCOLS = ['height_step', 'force_clamp', 'triangle', 'multisine', 'chirp', 'sines', 'staircase']


def draw_material(rng, rec, nterms, T):
    E_inst = rec['E_inst']
    E_rel = E_inst * rng.uniform(0.25, 0.85)
    Te = rec['Te']
    lo, hi = max(8 * T, 2e-5), 0.4 * Te
    for _ in range(200):
        lt = np.sort(rng.uniform(math.log(lo), math.log(hi), nterms))
        if nterms == 1 or np.min(np.diff(lt)) > math.log(3.5):
            break
    else:
        raise Fail('tau separation')
    taus = [float(v) for v in np.exp(lt)]
    w = rng.dirichlet(np.ones(nterms) * 2.0)
    w = np.maximum(w, 0.08); w /= w.sum()
    J_inst, J0 = 1 / E_inst, 1 / E_rel
    Js = [float(v) for v in (J0 - J_inst) * w]
    return {'J0': J0, 'J': Js, 'tau': taus, 'tau_window_s': [lo, hi]}


def draw_record(rng, effects, proto_hint=None):
    fx = set(effects)
    rec = {}
    N = int(rng.integers(8000, 40001))
    min_dur = 0.0
    if 'thermal_drift' in fx:
        min_dur = 2.0
    elif 'piezo_creep' in fx:
        min_dur = 0.5
    elif 'mains_interference' in fx:
        min_dur = 0.25
    fs_hi = min(1e5, N / min_dur) if min_dur > 0 else 1e5
    fs = logu(rng, 1e3, fs_hi)
    fs = float(round(fs, -1)) if fs > 2000 else float(round(fs))
    rec.update(N=N, fs=fs, T=1.0 / fs, dur=N / fs)
    rec['t0'] = 0.0 if rng.random() < 0.4 else float(round(rng.uniform(0.001, 60.0), 6))
    # protocol
    choices = list(PROTOCOLS)
    if 'instrument_resonance' in fx:
        choices = ['height_step', 'force_clamp', 'triangle', 'chirp', 'staircase']
    if 'piezo_hysteresis' in fx:
        choices = ['triangle', 'staircase', 'sines', 'multisine', 'chirp']
    if 'piezo_creep' in fx:
        choices = ['height_step', 'force_clamp', 'staircase', 'triangle', 'sines']
    kind = str(rng.choice(choices))
    if proto_hint:
        kind = proto_hint
    # phases
    fp, fa = rng.uniform(0.01, 0.04), rng.uniform(0.12, 0.25)
    fr, fq = rng.uniform(0.08, 0.15), rng.uniform(0.01, 0.04)
    rec['n_pre'] = int(fp * N); rec['n_a'] = int(fa * N); rec['n_r'] = int(fr * N); rec['n_post'] = int(fq * N)
    n_e = N - rec['n_pre'] - rec['n_a'] - rec['n_r'] - rec['n_post']
    rec['Te'] = n_e * rec['T']
    # material / tip / cantilever with a sensible operating point
    rec['nu'] = float(rng.choice([0.5, 0.5, 0.5, 0.5, 0.45, 0.4, 0.33]))
    ok = False
    for _ in range(40):
        rec['E_inst'] = logu(rng, 1e3, 1e7)
        nterms = 3 if 'missing_relaxation' in fx else int(rng.integers(1, 4))
        mat = draw_material(rng, rec, nterms, rec['T'])
        Jmid = 0.5 * (mat['J0'] + mat['J0'] - sum(mat['J']))
        for _ in range(60):
            if rng.random() < 0.55:
                tip = {'shape': 'sphere', 'radius_nm': float(round(logu(rng, 10, 5000), 2))}
            else:
                tip = {'shape': 'cone', 'half_angle_deg': float(round(rng.uniform(15, 40), 2))}
            phi = phi_declared(tip, rec['nu'])
            Kt = float(round(logu(rng, 0.01, 5.0), 4))
            dop = logu(rng, 5, 150)
            hop = phi.inv(Kt * dop * 1e9 * Jmid)
            if not (2 <= hop <= 3000):
                continue
            if tip['shape'] == 'sphere' and hop > 0.3 * tip['radius_nm']:
                continue
            kc = phi.vd(hop)[1] / (1e9 * Jmid)
            if not (0.05 <= kc / Kt <= 30):
                continue
            ok = True
            break
        if ok:
            break
    if not ok:
        raise Fail('operating point')
    rec.update(mat=mat, tip=tip, Kt=Kt, d_op=dop, h_op=hop, kc_over_Kt=kc / Kt)
    rec['delta_op'] = dop + hop
    Vop = logu(rng, 0.15, 2.5)
    Ct = float(round(min(max(dop / Vop, 5.0), 500.0), 3))
    rec['Ct'] = Ct
    rec['sigma_v'] = float(logu(rng, 3e-4, 4e-3))
    rec['sigma_v'] = min(rec['sigma_v'], dop / Ct / 60.0)
    rec['v0'] = float(rng.uniform(-0.5, 0.5)) if rng.random() < 0.5 else 0.0
    rec['g0'] = float(rec['delta_op'] * rng.uniform(0.8, 4.0) + rng.uniform(10, 60))
    rec['retract_extra'] = float(rec['g0'] * rng.uniform(0.0, 0.4))
    # protocol parameters
    p = {'kind': kind}
    Te = rec['Te']; fs = rec['fs']
    amp_max = 0.3 * math.sqrt(mat['J0'] - sum(mat['J'])) / math.sqrt(mat['J0']) + 0.1
    if kind == 'height_step':
        p.update(d1_frac=float(rng.uniform(0.3, 0.6)), step_at_frac=float(rng.uniform(0.1, 0.3)),
                 rise_samples=int(rng.integers(1, 6)))
    elif kind == 'triangle':
        p.update(amp_frac=float(rng.uniform(0.15, amp_max)), cycles=int(rng.integers(1, 7)))
    elif kind == 'staircase':
        p.update(amp_frac=float(rng.uniform(0.15, amp_max)), steps=int(rng.integers(3, 9)),
                 updown=bool(rng.random() < 0.6))
    elif kind == 'multisine':
        K = int(rng.integers(3, 9))
        flo = 3.0 / Te
        fhi = min(fs / 20, flo * 10 ** rng.uniform(1.5, 3.0))
        cyc = np.unique(np.round(np.geomspace(flo, fhi, K) * Te))
        fr = [float(c / Te) for c in cyc]
        ph = [float(-math.pi * k * (k - 1) / len(fr)) for k in range(1, len(fr) + 1)]   # Schroeder
        p.update(amp_frac=float(rng.uniform(0.1, amp_max)), freqs_hz=fr, phases_rad=ph)
    elif kind == 'chirp':
        f0 = 2.0 / Te * rng.uniform(1, 3)
        f1 = min(fs / 10, f0 * 10 ** rng.uniform(1.5, 3.2))
        p.update(amp_frac=float(rng.uniform(0.1, amp_max)), f0_hz=float(f0), f1_hz=float(f1))
    elif kind == 'sines':
        m = int(rng.integers(2, 5))
        flo = 5.0 * m / Te
        fhi = min(fs / 15, flo * 10 ** rng.uniform(1, 2.5))
        p.update(amp_frac=float(rng.uniform(0.1, amp_max)),
                 freqs_hz=[float(v) for v in np.geomspace(flo, fhi, m)])
    elif kind == 'force_clamp':
        p.update(sp1_nm=float(dop * rng.uniform(0.3, 0.6)), sp2_nm=float(dop),
                 hold1_samples=int(rng.uniform(0.1, 0.25) * n_e))
        p['v_app_nm_per_s'] = float((rec['g0'] + 0.7 * rec['delta_op']) / (rec['n_a'] * rec['T']))
        J_inst = mat['J0'] - sum(mat['J'])
        kc_i = phi.vd(hop)[1] / (1e9 * J_inst)
        fbw = min(rng.uniform(20, 300), fs / 80)
        p['bandwidth_hz'] = float(fbw)
        p['ki_per_s'] = float(2 * math.pi * fbw * (Kt + kc_i) / kc_i)
    rec['protocol'] = p
    # excursion used for sizing hysteresis thresholds
    rec['exc_pp_nm'] = float(2 * p.get('amp_frac', 0.3) * rec['delta_op'])
    # drive / piezo
    stroke = rec['g0'] + rec['delta_op'] * 1.6 + rec['retract_extra']
    if rng.random() < 0.6:
        rec['drive_col'] = 'drive_v'
        gain = max(logu(rng, 8, 400), stroke / 8.0)
        gain = float(round(gain, 3))
        v_lo = -9.5 + rec['retract_extra'] / gain
        v_hi = 9.5 - stroke / gain
        vstart = rng.uniform(v_lo, max(v_lo, v_hi))
        rec['gain'] = gain
        rec['x_off'] = float(vstart * gain)
        rec['dac_bits'] = int(rng.choice([0, 16, 18, 20]))
        rec['act_fn'] = logu(rng, 1000, 20000); rec['act_zeta'] = float(rng.uniform(0.3, 0.9))
    else:
        rec['drive_col'] = 'drive_nm'
        rec['gain'] = float(round(logu(rng, 8, 400), 3))
        rec['x_off'] = float(round(rng.uniform(-2000, 8000), 1))
        rec['dac_bits'] = 0
        rec['act_fn'] = logu(rng, 300, 5000); rec['act_zeta'] = float(rng.uniform(0.6, 1.0))
    rec['zs_abs'] = rec['x_off'] + rec['g0']
    # optional columns
    rec['has_ref'] = bool(rng.random() < 0.4)
    rec['sigma_ref'] = 0.0 if rng.random() < 0.3 else float(rec['sigma_v'] * rng.uniform(0.5, 1.5))
    rec['has_height'] = bool(rng.random() < 0.5)
    rec['sigma_height'] = 0.0 if rng.random() < 0.3 else float(logu(rng, 0.02, 1.0))
    rec['height_offset'] = 0.0 if rec['drive_col'] == 'drive_nm' and rng.random() < 0.5 else float(rng.uniform(-50, 50))
    rec['extra_col'] = str(rng.choice(['', '', '', 'segment', 'lateral_v', 'photodiode_sum_v']))
    rec['adc_bits'] = int(rng.choice([0, 0, 16, 18]))
    rec['pink_sigma_v'] = 0.0
    rec['col_shuffle'] = bool(rng.random() < 0.2)
    return rec


# ----------------------------------------------------------------------------------------------
# Effects: parameter draw + one "strength" knob each
# ----------------------------------------------------------------------------------------------
def effect_setup(e, rng, rec, base):
    """returns (knob0, knob_max, make(knob) -> (effdict_entry, mat_override, phi_override))"""
    T, fs = rec['T'], rec['fs']
    nomphi = phi_declared(rec['tip'], rec['nu'])
    href = base['h_ref']; hmax = base['h_max']
    mat = rec['mat']
    if e == 'piezo_hysteresis':
        pp = max(rec['exc_pp_nm'], 1.0)
        fr = np.array(sorted(rng.uniform(0.02, 0.6, 4)))
        wr = np.array([0.4, 0.3, 0.2, 0.1]) * rng.uniform(0.7, 1.3, 4)
        wr /= wr.sum()

        def make(k):
            return {'model': 'Prandtl-Ishlinskii (play operators), initial state as after a downward sweep',
                    'thresholds_nm': [float(v) for v in fr * pp], 'weights': [float(v) for v in wr * k],
                    'total_weight': float(k)}, None, None
        return 0.05, 0.3, make
    if e == 'piezo_creep':
        def make(k):
            return {'model': 'normalised log-creep: z = (x + g*sum_k LP_tau_k(x)) / (1 + g*K), one lag per decade',
                    'gamma_per_decade': float(k), 'taus_s': creep_taus(rec)}, None, None
        return 0.01, 0.06, make
    if e == 'thermal_drift':
        mode = str(rng.choice(['deflection', 'sample', 'both']))
        sg = lambda: float(rng.choice([-1, 1]))
        q = {'mode': mode, 'defl_rate_v_per_s': sg() * 1e-3, 'defl_curv_v_per_s': float(rng.uniform(-0.5, 0.5)) * 1e-3,
             'defl_settle_v': float(rng.uniform(-1, 1)) * 1e-3 * rec['dur'] * 0.3,
             'defl_settle_tau_s': float(rec['dur'] * rng.uniform(0.1, 0.5)),
             'sample_rate_nm_per_s': sg() * 1.0, 'sample_curv_nm_per_s': float(rng.uniform(-0.5, 0.5))}

        def make(k):
            d = dict(q); d['scale'] = float(k)
            d['model'] = 'deflection: k*(r t + c t^2/D + A(1-exp(-t/tau))) V ; sample height: k*(r t + c t^2/D) nm'
            return d, None, None
        return 1.0, 10.0, make
    if e == 'missing_relaxation':
        lo, hi = mat['tau_window_s']
        lt = np.log(mat['tau'])
        sep = math.log(3.0)
        slots = []
        if math.log(lo) < lt[0] - sep:
            slots.append((math.log(lo), lt[0] - sep))
        if lt[-1] + sep < math.log(hi):
            slots.append((lt[-1] + sep, math.log(hi)))
        for a, b in zip(lt[:-1], lt[1:]):
            if b - a > 2 * sep:
                slots.append((a + sep, b - sep))
        if not slots:
            raise Fail('no slot for missing tau')
        a, b = slots[int(rng.integers(len(slots)))]
        tau4 = float(math.exp(rng.uniform(a, b)))
        tt = np.geomspace(5 * T, rec['Te'], 200)
        Jn = mat_J(mat, tt)

        def make(k):
            J4 = k * (mat['J0'] - (mat['J0'] - sum(mat['J'])))
            m4 = {'J0': mat['J0'] + J4, 'J': mat['J'] + [J4], 'tau': mat['tau'] + [tau4]}
            Jt = mat_J(m4, tt)
            kap = float(np.sum(Jt * Jn) / np.sum(Jt * Jt))
            mt = mat_scale(m4, kap)
            return {'model': 'extra Prony term; whole 4-term compliance rescaled (LS over log-spaced t) to best match the 3-term nominal',
                    'tau4_s': tau4, 'J4_rel_to_sumJ': float(k), 'kappa': kap}, mt, None
        return 0.4, 3.0, make
    if e == 'instrument_resonance':
        kind = str(rng.choice(['stage', 'holder']))
        for _ in range(50):
            fr = logu(rng, max(100.0, 0.02 * fs), min(30000.0, 0.3 * fs))
            if abs(math.log(fr / rec['act_fn'])) > math.log(1.6):
                break
        else:
            raise Fail('resonance placement')
        Q = logu(rng, 5, 40)

        def make(k):
            return {'kind': kind, 'f_hz': float(fr), 'Q': float(Q), 'a': float(k),
                    'model': ('stage: actuator x [1 + a(w^2/(s^2+ws/Q+w^2) - 1)]' if kind == 'stage' else
                              'holder: deflection += a * (-s^2/(s^2+ws/Q+w^2)) z_actuator (base-excited mode, also in reference)')}, None, None
        return 0.02, (0.4 if kind == 'stage' else 0.2), make
    if e == 'adhesion':
        Pop = rec['Kt'] * rec['d_op']
        lf = rng.uniform(1.5, 3.0)
        Lx = rng.uniform(1.0, 8.0)
        gap_end = rec['g0'] + rec['retract_extra']
        kmax = min(1.2, (0.7 * gap_end - Lx) * rec['Kt'] / (lf * Pop))

        def make(k):
            F = k * Pop
            return {'model': 'DMT constant adhesion in contact + capillary-like neck F=Fad(1-g/L) on retract',
                    'F_ad_nN': float(F), 'neck_length_nm': float(lf * F / rec['Kt'] + Lx), 'F_ad_over_P_op': float(k)}, None, None
        # physically meaningful minimum: 3 % of the operating load
        return 0.06, kmax, make, 0.03
    if e == 'tip_geometry':
        shp = rec['tip']['shape']; nu = rec['nu']
        if shp == 'sphere':
            var = str(rng.choice(['worn_sphere', 'power_law', 'exact_small_sphere']))
        else:
            var = str(rng.choice(['blunted_cone', 'power_law', 'truncated_cone']))
        sign = float(rng.choice([-1, 1]))
        R = rec['tip'].get('radius_nm', 0.0)
        al = math.radians(rec['tip'].get('half_angle_deg', 20.0))

        def make(k):
            info = {'variant': var}
            if var == 'worn_sphere':
                aref = math.sqrt(R * href)
                a0 = k * 0.9 * aref
                fp = lambda r: np.where(r < a0, 0.0, r / np.sqrt(np.maximum(R * R - r * r, 1e-30)))
                ag = a0 + (0.97 * R - a0) * np.geomspace(1e-7, 1, 500)
                hh, pp = phi_sneddon(fp, ag, nu)
                ph = Phi(hh, pp)
                info.update(true_radius_nm=R, flat_radius_nm=float(a0))
            elif var == 'exact_small_sphere':
                Rt = hmax / (0.15 + 0.7 * k)
                fp = lambda r: r / np.sqrt(np.maximum(Rt * Rt - r * r, 1e-30))
                ag = np.geomspace(1e-4, 0.985, 500) * Rt
                hh, pp = phi_sneddon(fp, ag, nu)
                ph = Phi(hh, pp)
                info.update(true_radius_nm=float(Rt), profile='exact sphere (not paraboloid)')
            elif var == 'power_law':
                if shp == 'sphere':
                    n = 2.0 + sign * 1.2 * k if sign > 0 else 2.0 - 0.7 * k
                else:
                    n = 1.0 + 0.8 * k
                ph = phi_powerlaw(n, 1.0, nu)
                info.update(profile_exponent=float(n), profile='z = B r^n')
            elif var == 'blunted_cone':
                ht = k * 2.5 * href
                Rb = ht / (1 - math.sin(al))
                rt = Rb * math.cos(al)
                cot = 1 / math.tan(al)
                fp = lambda r: np.where(r < rt, r / np.sqrt(np.maximum(Rb * Rb - r * r, 1e-30)), cot)
                ag = np.geomspace(1e-4 * rt, 200 * rt + 10 * hmax * math.tan(al), 600)
                hh, pp = phi_sneddon(fp, ag, nu)
                ph = Phi(hh, pp)
                info.update(blunt_radius_nm=float(Rb), half_angle_deg=rec['tip']['half_angle_deg'])
            else:  # truncated cone (worn flat apex)
                aref = 2 * href * math.tan(al) / math.pi
                a0 = k * 0.9 * aref
                cot = 1 / math.tan(al)
                fp = lambda r: np.where(r < a0, 0.0, cot)
                ag = a0 + (50 * aref + 10 * hmax * math.tan(al)) * np.geomspace(1e-7, 1, 500)
                hh, pp = phi_sneddon(fp, ag, nu)
                ph = Phi(hh, pp)
                info.update(flat_radius_nm=float(a0), half_angle_deg=rec['tip']['half_angle_deg'])
            kap = ph.val(href) / nomphi.val(href)
            info['kappa'] = float(kap)
            info['model'] = 'Sneddon/Galin contact for the true profile; true compliance = kappa x nominal-equivalent so the load matches at h_ref'
            return info, mat_scale(mat, kap), ph
        return 0.35, 1.0, make
    if e == 'hydrodynamic_drag':
        rb = rng.uniform(0.2, 2.0); H = rng.uniform(3000, 15000)

        def make(k):
            return {'model': 'F = (b_inf + b_near*H/(gap+H)) * dz_actuator/dt on the lever (adds to the bending, not to the tip load)',
                    'beta_inf_Nspm': float(k), 'beta_near_Nspm': float(k * rb), 'tip_height_nm': float(H),
                    'viscosity_hint': 'liquid (water-like)'}, None, None
        return 1e-6, 2e-4, make
    if e == 'channel_delay':
        integer = bool(rng.random() < 0.5)
        cap = max(4.0, min(150.0, 0.003 * fs))

        def make(k):
            D = float(round(k)) if integer else float(k)
            D = max(D, 1.0) if integer else D
            return {'model': 'deflection channel delayed by D samples (cubic Lagrange for the fractional part); reference not delayed',
                    'delay_samples': D, 'delay_s': D * T, 'integer': integer}, None, None
        return 1.5, cap, make
    if e == 'mains_interference':
        f = float(rng.choice([50.0, 60.0]) * (1 + rng.uniform(-3e-4, 3e-4)))
        hr = [1.0, float(rng.uniform(0.05, 0.4)), float(rng.uniform(0.1, 0.7)), float(rng.uniform(0.0, 0.25))]
        ph = [float(v) for v in rng.uniform(0, 2 * math.pi, 4)]

        def make(k):
            return {'model': 'sum of harmonics 1..4 of the mains frequency, added to deflection_v',
                    'f_hz': f, 'amp_v': float(k), 'harmonic_rel': hr, 'phases_rad': ph}, None, None
        return rec['sigma_v'], 0.05, make
    if e == 'detector_nonlinearity':
        kind = str(rng.choice(['poly', 'poly', 'tanh']))
        r3 = float(rng.uniform(-1, 1)); s2 = float(rng.choice([-1, 1]))

        def make(k):
            if kind == 'poly':
                return {'kind': 'poly', 'a2': float(s2 * k), 'a3': float(r3 * k),
                        'model': 'V = v + a2 v^2/10 + a3 v^3/100 (v = linear signal incl. offset), baseline re-zeroed; also on reference'}, None, None
            return {'kind': 'tanh', 'inv_vsat': float(k), 'model': 'V = Vs tanh(v/Vs), baseline re-zeroed; also on reference'}, None, None
        return (0.05 if kind == 'poly' else 0.05), (0.3 if kind == 'poly' else 0.6), make
    if e == 'substrate_effect':
        shp = rec['tip']['shape']; nu = rec['nu']

        def make(k):
            if shp == 'sphere':
                R = rec['tip']['radius_nm']
                t_f = math.sqrt(R * href) / k
                chi = np.sqrt(R * HGRID) / t_f
                corr = 1 + 1.133 * chi + 1.283 * chi ** 2 + 0.769 * chi ** 3 + 0.0975 * chi ** 4
                mdl = 'bonded film, Dimitriadis 2002: F = F_Hertz (1+1.133x+1.283x^2+0.769x^3+0.0975x^4), x = sqrt(R h)/t'
            else:
                t_f = href / k
                tn = math.tan(math.radians(rec['tip']['half_angle_deg']))
                q = HGRID / t_f
                corr = 1 + 1.7795 * (2 * tn / math.pi ** 2) * q + 16 * 1.7795 ** 2 * tn ** 2 * q ** 2
                mdl = 'bonded film, Gavara-Chadwick 2012 cone correction (to 2nd order in h/t)'
            ph = Phi(HGRID, nomphi.val(1.0) * HGRID ** (1.5 if shp == 'sphere' else 2.0) * corr)
            kap = ph.val(href) / nomphi.val(href)
            return {'model': mdl, 'film_thickness_nm': float(t_f), 'knob': float(k), 'kappa': float(kap)}, mat_scale(mat, kap), ph
        if shp == 'sphere':
            return 0.2, 1.0, make
        return 0.1, 0.5, make
    raise ValueError(e)


# ----------------------------------------------------------------------------------------------
def ratio_of(a, b, sigma):
    m = a['contact'] | b['contact']
    if m.sum() < 10:
        return 0.0
    return float(np.sqrt(np.mean((a['V'][m] - b['V'][m]) ** 2)) / sigma)


def run_pair(rec, eff, mat_true, phi_true, rng_proto):
    """drive generated by the system with the effects; nominal replay of the same drive"""
    nomphi = phi_declared(rec['tip'], rec['nu'])
    drive, xcmd = make_drive(rec, eff, mat_true, phi_true, rng_proto)
    se = simulate(rec, xcmd, eff, mat_true, phi_true)
    sn = simulate(rec, xcmd, {}, rec['mat'], nomphi)
    return drive, xcmd, se, sn


def check_nominal(rec, s):
    """nominal run sanity: out of contact at the start and end, in contact during excitation"""
    c = s['contact']; N = rec['N']
    if c[:rec['n_pre'] + 2].any() or c[-max(3, rec['n_post']):].any():
        raise Fail('contact at ends')
    a = rec['n_pre'] + rec['n_a']; b = N - rec['n_r'] - rec['n_post']
    if c[a:b].mean() < 0.98:
        raise Fail('lost contact during excitation %.3f' % c[a:b].mean())
    if np.max(np.abs(s['V'])) > 9.0:
        raise Fail('deflection out of range')
    if rec['has_ref'] and np.max(np.abs(s['Vref'])) > 9.5:
        rec['has_ref'] = False


def build_record(idx, effects, targets, pink, proto_hint=None):
    last = None
    for attempt in range(25):
        rng = np.random.default_rng([SEED, idx, attempt])
        try:
            rec = draw_record(rng, effects, proto_hint)
            rec['pink'] = pink
            nomphi = phi_declared(rec['tip'], rec['nu'])
            _, xc0, s0, _ = run_pair(rec, {}, rec['mat'], nomphi, rng)
            check_nominal(rec, s0)
            hc = s0['h'][s0['contact']]
            base = {'h_ref': float(np.median(hc)), 'h_max': float(np.max(hc))}
            rec['h_ref'] = base['h_ref']; rec['h_max_nominal'] = base['h_max']
            setups = {}
            eff = {}; mat_true = rec['mat']; phi_true = nomphi
            indiv = {}
            for e, tgt in zip(effects, targets):
                su = effect_setup(e, rng, rec, base)
                k0, kmax, make = su[:3]
                kmin = su[3] if len(su) > 3 else 0.0
                if kmax <= kmin:
                    raise Fail('%s: no admissible strength' % e)
                pts = []
                k = max(kmin, min(k0, kmax))
                best = None
                for it in range(7):
                    pe, mt, pt = make(k)
                    e1 = {e: pe}
                    _, _, se, sn = run_pair(rec, e1, mt or rec['mat'], pt or nomphi, rng)
                    r = ratio_of(se, sn, rec['sigma_v'])
                    pts.append((k, r))
                    if best is None or abs(math.log(max(r, 1e-9) / tgt)) < abs(math.log(max(best[1], 1e-9) / tgt)):
                        best = (k, r)
                    if abs(math.log(max(r, 1e-12) / tgt)) < math.log(1.12):
                        break
                    if r <= 1e-9:
                        k = min(kmax, k * 10); continue
                    p = 1.0
                    if len(pts) >= 2:
                        (ka, ra), (kb, rb) = pts[-2], pts[-1]
                        if ka != kb and ra > 0 and rb > 0 and ra != rb:
                            p = min(3.0, max(0.3, math.log(rb / ra) / math.log(kb / ka)))
                    kn = k * (tgt / r) ** (1.0 / p)
                    kn = max(kmin, min(kmax, kn))
                    if kn == k:
                        break
                    k = kn
                k, r = best
                if r < 0.7 * tgt or r > 1.6 * tgt:
                    raise Fail('could not size %s (ratio %.2f, target %.2f, knob %.3g / max %.3g)' % (e, r, tgt, k, kmax))
                pe, mt, pt = make(k)
                eff[e] = pe; indiv[e] = r
                if mt is not None:
                    mat_true = mt
                if pt is not None:
                    phi_true = pt
            drive, xcmd, se, sn = run_pair(rec, eff, mat_true, phi_true, rng)
            if effects:
                c = se['contact']; a = rec['n_pre'] + rec['n_a']; b = rec['N'] - rec['n_r'] - rec['n_post']
                if c[:rec['n_pre'] + 2].any() or c[-max(3, rec['n_post']):].any():
                    raise Fail('effect run: contact at ends')
                if c[a:b].mean() < 0.95:
                    raise Fail('effect run: lost contact')
                if np.max(np.abs(se['V'])) > 9.5:
                    raise Fail('effect run out of range')
            ratio = ratio_of(se, sn, rec['sigma_v']) if effects else 0.0
            return rec, eff, mat_true, drive, se, sn, ratio, indiv, attempt, np.random.default_rng([SEED, idx, attempt, 99])
        except Fail as ex:
            last = str(ex)
            continue
    raise RuntimeError('record %d (%s) failed: %s' % (idx, effects, last))


# ----------------------------------------------------------------------------------------------
def pink_noise(rng, n, sigma):
    f = np.fft.rfftfreq(n)
    X = rng.normal(size=len(f)) + 1j * rng.normal(size=len(f))
    f[0] = f[1]
    X /= np.sqrt(f)
    X[0] = 0
    x = np.fft.irfft(X, n)
    return x / np.std(x) * sigma


def write_record(outdir, name, rec, drive, se, nrng):
    N = rec['N']; fs = rec['fs']
    t = rec['t0'] + np.arange(N) / fs
    V = se['V'] + nrng.normal(0, rec['sigma_v'], N)
    if rec['pink_sigma_v'] > 0:
        V = V + pink_noise(nrng, N, rec['pink_sigma_v'])
    if rec['adc_bits']:
        lsb = 2 * VFS / 2 ** rec['adc_bits']
        V = np.round(V / lsb) * lsb
    cols = [('time_s', t, '%.12f'), (rec['drive_col'], drive, '%.9g'), ('deflection_v', V, '%.8g')]
    if rec['has_ref']:
        Vr = se['Vref'] + (nrng.normal(0, rec['sigma_ref'], N) if rec['sigma_ref'] > 0 else 0)
        cols.append(('reference_deflection_v', Vr, '%.8g'))
    if rec['has_height']:
        H = se['z'] + rec['height_offset'] + (nrng.normal(0, rec['sigma_height'], N) if rec['sigma_height'] > 0 else 0)
        cols.append(('measured_height_nm', H, '%.6f'))
    ex = rec['extra_col']
    if ex == 'segment':
        seg = np.zeros(N); a = rec['n_pre'] + rec['n_a']; b = N - rec['n_r'] - rec['n_post']
        seg[a:b] = 1; seg[b:] = 2
        cols.append(('segment', seg, '%d'))
    elif ex == 'lateral_v':
        cols.append(('lateral_v', 0.02 * np.sin(np.arange(N) / 977.0) + nrng.normal(0, 1e-3, N), '%.6g'))
    elif ex == 'photodiode_sum_v':
        cols.append(('photodiode_sum_v', 4.2 + nrng.normal(0, 2e-3, N), '%.6g'))
    if rec['col_shuffle']:
        order = list(nrng.permutation(len(cols)))
        cols = [cols[i] for i in order]
    header = ','.join(c[0] for c in cols)
    arr = np.column_stack([c[1] for c in cols])
    fmt = ','.join(c[2] for c in cols)
    np.savetxt(os.path.join(outdir, name + '.csv'), arr, fmt=fmt, delimiter=',', header=header, comments='')
    # sidecar
    L = ['format = "recording/1"', 'sample_rate_hz = %r' % float(fs), '',
         '[cantilever]', 'spring_constant_n_per_m = %r' % rec['Kt'],
         'deflection_sensitivity_nm_per_v = %r' % rec['Ct']]
    if rec['toml_extra']:
        L.append('resonance_hz = %r' % float(round(rec['toml_extra'], 1)))
    L += ['', '[tip]', 'shape = "%s"' % rec['tip']['shape']]
    if rec['tip']['shape'] == 'sphere':
        L.append('radius_nm = %r' % rec['tip']['radius_nm'])
    else:
        L.append('half_angle_deg = %r' % rec['tip']['half_angle_deg'])
    if rec['drive_col'] == 'drive_v' or rec['gain_in_toml']:
        L += ['', '[piezo]', 'gain_nm_per_v = %r' % rec['gain']]
    L += ['', '[sample]', 'name = "%s"' % rec['sample_name'], 'poisson_ratio = %r' % rec['nu'], '',
          '[notes]', 'operator = "blind-sim4"', 'protocol = "%s"' % rec['protocol']['kind']]
    with open(os.path.join(outdir, name + '.toml'), 'w') as f:
        f.write('\n'.join(L) + '\n')
    return [c[0] for c in cols]


def jsonable(o):
    if isinstance(o, dict):
        return {str(k): jsonable(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [jsonable(v) for v in o]
    if isinstance(o, (np.floating,)):
        return float(o)
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, np.bool_):
        return bool(o)
    if isinstance(o, np.ndarray):
        return jsonable(o.tolist())
    return o


def plan():
    rng = np.random.default_rng([SEED, 7777])
    pairs = [('piezo_hysteresis', 'piezo_creep'), ('adhesion', 'substrate_effect'),
             ('thermal_drift', 'mains_interference'), ('missing_relaxation', 'hydrodynamic_drag'),
             ('tip_geometry', 'detector_nonlinearity'), ('channel_delay', 'instrument_resonance')]
    items = []
    for p in pairs:
        a = logu(rng, 3.5, 6.0); b = logu(rng, 2.0, 0.75 * a)
        items.append((list(p), [a, b], False, None))
    singles = IDS * 2 + [IDS[i] for i in rng.permutation(12)[:10]]
    for e in singles:
        items.append(([e], [logu(rng, 2.0, 6.0)], False, None))
    nprot = [PROTOCOLS[i] for i in rng.permutation(len(PROTOCOLS))[:6]]
    for i in range(6):
        items.append(([], [], i % 2 == 1, nprot[i]))
    order = rng.permutation(len(items))
    return [items[i] for i in order]


SAMPLES = ['PDMS', 'polyacrylamide gel', 'agarose gel', 'hydrogel', 'PDMS 1:20', 'polymer gel', 'soft PU',
           'gelatin', 'collagen gel', 'elastomer']


def main():
    if len(sys.argv) != 2:
        print('usage: sim.py OUTDIR'); sys.exit(2)
    out = sys.argv[1]
    os.makedirs(os.path.join(out, 'recs'), exist_ok=True)
    t_start = time.time()
    truth = []
    items = plan()
    assert len(items) == N_RECORDS
    for idx, (effects, targets, pink, hint) in enumerate(items):
        t1 = time.time()
        name = 'rec%02d' % idx
        rec, eff, mat_true, drive, se, sn, ratio, indiv, attempt, nrng = build_record(idx, effects, targets, pink, hint)
        mrng = np.random.default_rng([SEED, idx, attempt, 5])
        if pink:
            rec['pink_sigma_v'] = float(rec['sigma_v'] * mrng.uniform(0.5, 2.0))
        elif effects and mrng.random() < 0.2:
            rec['pink_sigma_v'] = float(rec['sigma_v'] * mrng.uniform(0.3, 1.0))
        rec['toml_extra'] = float(mrng.uniform(5e3, 3e5)) if mrng.random() < 0.2 else 0.0
        rec['gain_in_toml'] = bool(mrng.random() < 0.3)
        rec['sample_name'] = str(mrng.choice(SAMPLES))
        cols = write_record(os.path.join(out, 'recs'), name, rec, drive, se, nrng)
        order = sorted(effects, key=lambda e: -indiv[e])
        c = se['contact'] | sn['contact']
        params = {
            'fs_hz': rec['fs'], 'n_samples': rec['N'], 't0_s': rec['t0'],
            'drive_column': rec['drive_col'], 'columns': cols,
            'protocol': rec['protocol'],
            'phases_samples': {'pre': rec['n_pre'], 'approach': rec['n_a'],
                               'excitation': rec['N'] - rec['n_pre'] - rec['n_a'] - rec['n_r'] - rec['n_post'],
                               'retract': rec['n_r'], 'post': rec['n_post']},
            'material_true': {'J0_per_Pa': mat_true['J0'], 'J_per_Pa': mat_true['J'], 'tau_s': mat_true['tau'],
                              'E_inst_Pa': 1.0 / (mat_true['J0'] - sum(mat_true['J'])), 'E_relaxed_Pa': 1.0 / mat_true['J0']},
            'material_nominal_equivalent': {'J0_per_Pa': rec['mat']['J0'], 'J_per_Pa': rec['mat']['J'], 'tau_s': rec['mat']['tau'],
                                            'E_inst_Pa': 1.0 / (rec['mat']['J0'] - sum(rec['mat']['J'])),
                                            'E_relaxed_Pa': 1.0 / rec['mat']['J0']},
            'tip_declared': rec['tip'], 'tip_true': eff.get('tip_geometry', rec['tip']),
            'poisson_ratio': rec['nu'],
            'cantilever': {'k_n_per_m': rec['Kt'], 'C_nm_per_v': rec['Ct']},
            'piezo': {'gain_nm_per_v': rec['gain'], 'dyn_fn_hz': rec['act_fn'], 'dyn_zeta': rec['act_zeta'],
                      'model': '2nd-order low-pass, unit DC gain, ZOH-discretised', 'dac_bits': rec['dac_bits']},
            'geometry_nm': {'approach_gap': rec['g0'], 'surface_abs': rec['zs_abs'], 'x_offset': rec['x_off'],
                            'retract_beyond_start': rec['retract_extra'], 'delta_op': rec['delta_op'],
                            'h_op': rec['h_op'], 'd_op': rec['d_op'], 'h_ref_nominal_median': rec['h_ref'],
                            'h_max_nominal': rec['h_max_nominal']},
            'noise': {'deflection_white_sigma_v': rec['sigma_v'], 'deflection_pink_sigma_v': rec['pink_sigma_v'],
                      'reference_sigma_v': rec['sigma_ref'] if rec['has_ref'] else None,
                      'height_sigma_nm': rec['sigma_height'] if rec['has_height'] else None,
                      'adc_bits': rec['adc_bits']},
            'deflection_offset_v': rec['v0'], 'height_offset_nm': rec['height_offset'] if rec['has_height'] else None,
            'effects': eff, 'individual_ratios': indiv, 'targets': dict(zip(effects, targets)),
            'in_contact_samples': int(c.sum()), 'attempt': attempt,
            'ratio_vs_same_material_nominal': None,
        }
        if any(e in eff for e in ('tip_geometry', 'substrate_effect', 'missing_relaxation')):
            nomphi = phi_declared(rec['tip'], rec['nu'])
            xc = drive * rec['gain'] if rec['drive_col'] == 'drive_v' else drive
            s2 = simulate(rec, xc, {}, mat_true, nomphi)
            params['ratio_vs_same_material_nominal'] = ratio_of(se, s2, rec['sigma_v'])
        notes = ('null, white noise only' if not effects and not pink else
                 'null, white + 1/f noise' if not effects else
                 ' + '.join('%s (%.2f)' % (e, indiv[e]) for e in order))
        if rec['pink_sigma_v'] > 0 and effects:
            notes += '; also 1/f noise on deflection'
        truth.append(jsonable({'name': name, 'effects': order, 'ratio': ratio, 'params': params, 'notes': notes}))
        print('%s %-45s ratio %5.2f  %-11s fs %7.0f N %5d %-8s att %d  %.1fs' % (
            name, ','.join(order) or '-', ratio, rec['protocol']['kind'], rec['fs'], rec['N'], rec['drive_col'],
            attempt, time.time() - t1), flush=True)
    with open(os.path.join(out, 'truth.json'), 'w') as f:
        json.dump(truth, f, indent=1)
    print('total %.1f s' % (time.time() - t_start))


if __name__ == '__main__':
    main()
