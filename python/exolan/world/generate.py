"""One trial of the simulated world, evaluated analytically in time, and the writer of layout 1.

Kinematics first (tasks.py), then forces, then the torques that inverse dynamics of the coupled
system requires:

    tau_tot  = H(q) qdd + c(q, qd) + g(q; g_eff) - J^T f          (what all actuators supply)
    tau_e,app= exoskeleton torque acting on the limb
    tau_h    = tau_tot - tau_e,app + (friction effects)           (the human, N m)

and the recorded channels: moment = tau_h / mass, exo torque as recorded, encoder angles, insole.
Everything is a closed-form function of t (Fourier templates, sums of sinusoids, Gaussian bumps),
so quantities at earlier times (the exoskeleton controller's lag, an actuation delay) are
evaluated exactly instead of interpolated.
"""
from __future__ import annotations

import numpy as np
from scipy.signal import butter, filtfilt

from . import dynamics as dyn
from .anthropometry import G, User, leg_params
from .effects import COULOMB_EPS, Effect
from .tasks import TASK_SPECS, Smooth, fourier_eval, fourier_of_keypoints

FS = 200.0
DT = 1.0 / FS
SIDES = ("l", "r")
EXO_LIMIT = 15.0       # N m
PAD = 0.5              # s of pre-roll before t = 0 for lags/delays

# sensor noise (noise=True)
ENC_NOISE_DEG = 0.01   # encoder noise, deg (white; a 14-bit encoder quantises at 0.022 deg)
VEL_CUTOFF_HZ = 20.0   # velocity = zero-lag 2nd-order Butterworth (filtfilt) of the angle's derivative
FORCE_NOISE_N = 4.0
COP_NOISE_M = 0.002
COP_MIN_FORCE = 20.0   # N: below this the insole cannot locate the CoP (NaN)
EXO_NOISE_NM = 0.05
MOMENT_NOISE = 0.02    # N m/kg, low-passed at 8 Hz (ID noise is smooth)


def soft_clip(x, lim=EXO_LIMIT, p=6):
    """A smooth saturation at +-lim (the actuator's torque limit)."""
    return x / (1.0 + np.abs(x / lim) ** p) ** (1.0 / p)


def play(q, width):
    """Backlash (play) operator: the output follows the input only when the gap exceeds width/2."""
    out = np.empty_like(q)
    y = q[0]
    h = width / 2
    for i, x in enumerate(q):
        if x - y > h:
            y = x - h
        elif y - x > h:
            y = x + h
        out[i] = y
    return out


class TrialWorld:
    """The world of one (user, task) trial: both legs, closed-form in time."""

    def __init__(self, user: User, task: str, rng: np.random.Generator, effects: list[Effect] = ()):
        self.user, self.task = user, task
        self.spec = spec = TASK_SPECS[task]
        st = user.style
        self.M = user.mass
        self.Mc = user.mass * (1.0 + spec.carry)   # body + carried load
        # effects of this subject, per joint index
        self.fx = {j: {} for j in range(2)}
        for e in effects:
            if e.applies_to(user.name):
                self.fx[("hip", "knee").index(e.joint)][e.effect] = e.value
        base = leg_params(user, exo=True, seg_scale=st["seg_scale"])
        if "payload" in self.fx[0]:
            base = base.with_payload("thigh", self.fx[0]["payload"])
        if "payload" in self.fx[1]:
            base = base.with_payload("shank", self.fx[1]["payload"])
        self.p = base
        # templates with the user's style, a small left/right asymmetry
        per = spec.period * (st["period"] if spec.duty < 1 else rng.uniform(0.85, 1.15))
        self.T0 = per * rng.uniform(0.97, 1.03)
        self.coef = []  # [side][joint]
        for s in range(2):
            cs = []
            for j, kp in enumerate((spec.hip, spec.knee)):
                c = fourier_of_keypoints(kp)
                h = st["harm"][j]
                amp = st["amp"] * rng.uniform(0.95, 1.05)
                c[1:] = amp * c[1:] * (1 + 0.5 * np.concatenate([h, h]) + rng.normal(0, 0.02, size=len(c) - 1))
                c[0] += (st["hip_off"], st["knee_off"])[j] + rng.normal(0, 1.0)
                cs.append(c)
            self.coef.append(cs)
        self.rate = Smooth(rng, spec.rate_var, (3 * per, 10 * per))
        self.amp = [[Smooth(rng, spec.amp_var, (2 * per, 8 * per)) for _ in range(2)] for _ in range(2)]
        self.off = [[Smooth(rng, 2.0, (4.0, 15.0)) for _ in range(2)] for _ in range(2)]  # deg
        self.bumps = []
        if spec.bumps:
            rate, ah, ak, w = spec.bumps
            for s in range(2):
                n = rng.poisson(rate * 200.0)
                tb = rng.uniform(-PAD - 1.0, 199.0, size=n)
                self.bumps.append((tb, rng.uniform(0.4, 1.0, n) * ah * rng.choice([-0.5, 1.0], n),
                                   rng.uniform(0.4, 1.0, n) * ak, w * rng.uniform(0.7, 1.4, n)))
        self.load_coef = fourier_of_keypoints(spec.load) if spec.load else None
        self.shift = Smooth(rng, spec.shift, (2.0, 8.0))
        self.lean = Smooth(rng, spec.lean, (spec.period, 3 * spec.period)) if spec.lean else None
        self.sway = [Smooth(rng, 1.0, (1.0, 6.0)) for _ in range(2)]
        self.gait_offset = 0.055 * rng.uniform(0.85, 1.15)  # m, GRF aim ahead/behind the hip
        self.load_style = st["load"]
        self.tilt0 = 8.0 + rng.normal(0.0, 2.0)  # deg, anterior pelvic tilt when upright
        self.cop_off = st["cop_off"]
        # force profile normalisation over a stance
        s = np.linspace(0, 1, 2001)
        self.shape_mean = float(np.mean(self._shape(s)))
        # exoskeleton controller: a lagged, modulated share of the required torque + its own wiggle
        self.exo_lag = rng.uniform(0.015, 0.03)
        self.exo_gain = np.array([0.14, 0.14]) * st["assist"]
        self.exo_mod = [[Smooth(rng, 0.35, (3.0, 12.0)) for _ in range(2)] for _ in range(2)]
        self.exo_wiggle = [[Smooth(rng, 2.5, (0.15, 0.8), n=4) for _ in range(2)] for _ in range(2)]

    # --- kinematics ---------------------------------------------------------------------
    def _shape(self, s):
        sp = self.spec
        base = np.sin(np.pi * s) + sp.k3 * np.sin(3 * np.pi * s)
        return base + sp.impact * 2.5 * np.sin(np.pi * s) * np.exp(-s / 0.08)

    def phase(self, t):
        """phi, phid, phidd of the common cycle (both legs)."""
        w = 2 * np.pi / self.T0
        phi = w * (t + self.rate.integral(t))
        return phi, w * (1 + self.rate(t)), w * self.rate(t, 1)

    def kinematics(self, t):
        """q, qd, qdd (T, 2 sides, 2 joints) in rad, and each leg's cycle fraction (T, 2)."""
        t = np.asarray(t, float)
        phi, phid, phidd = self.phase(t)
        sign = -1.0 if self.spec.reverse else 1.0
        q = np.empty(t.shape + (2, 2))
        qd, qdd = np.empty_like(q), np.empty_like(q)
        frac = np.empty(t.shape + (2,))
        lift = np.zeros(t.shape + (2,))  # how much each leg is in an irregular event (0..1)
        for s in range(2):
            psi = sign * (phi + 2 * np.pi * self.spec.offset * s)
            psid, psidd = sign * phid, sign * phidd
            frac[:, s] = np.mod(psi / (2 * np.pi), 1.0)
            for j in range(2):
                c = self.coef[s][j]
                F, F1, F2 = fourier_eval(c, psi)
                A, Ad, Add = 1 + self.amp[s][j](t), self.amp[s][j](t, 1), self.amp[s][j](t, 2)
                O = self.off[s][j]
                x = c[0] + O(t) + A * F
                xd = O(t, 1) + Ad * F + A * F1 * psid
                xdd = O(t, 2) + Add * F + 2 * Ad * F1 * psid + A * (F2 * psid ** 2 + F1 * psidd)
                if self.bumps:
                    tb, ah, ak, w = self.bumps[s]
                    keep = (tb > t.min() - 5 * w) & (tb < t.max() + 5 * w)  # only events near these times
                    tb, ah, ak, w = tb[keep], ah[keep], ak[keep], w[keep]
                    near = np.abs(np.subtract.outer(t, tb)) < 5 * w
                    u = np.where(near, np.subtract.outer(t, tb) / w, 0.0)
                    g = np.where(near, np.exp(-0.5 * u * u), 0.0)
                    a = (ah, ak)[j]
                    x = x + g @ a
                    xd = xd + (g * (-u / w)) @ a
                    xdd = xdd + (g * (u * u - 1) / w ** 2) @ a
                    # the leg is unloaded over a wider window than the bump itself, so its
                    # accelerations do not push the pelvis while it still carries weight
                    lift[:, s] = np.minimum(np.where(near, np.exp(-0.5 * (u / 1.8) ** 2), 0.0).sum(1), 1.0)
                q[:, s, j], qd[:, s, j], qdd[:, s, j] = np.radians(x), np.radians(xd), np.radians(xdd)
        self._lift = lift
        return q, qd, qdd, frac

    # --- forces and required torques ---------------------------------------------------------
    def core(self, t):
        """Everything at times t: kinematics, pelvis acceleration, GRF, CoP, tau_tot (T, 2, 2)."""
        t = np.asarray(t, float)
        sp, p = self.spec, self.p
        q_rel, qd_rel, qdd_rel, frac = self.kinematics(t)
        # The pelvis tilts forward with the mean hip flexion (the trunk leans into squats and
        # landings). The chain hangs from the pelvis, so its dynamics depend on the thigh's
        # absolute angle q_hip - tilt (and its rates); knee and everything relative stay as they are.
        tilt = np.radians(self.tilt0) + sp.tilt * q_rel[:, :, 0].mean(1)
        tilt_d = sp.tilt * qd_rel[:, :, 0].mean(1)
        tilt_dd = sp.tilt * qdd_rel[:, :, 0].mean(1)
        q, qd, qdd = q_rel.copy(), qd_rel.copy(), qdd_rel.copy()
        q[:, :, 0] -= tilt[:, None]
        qd[:, :, 0] -= tilt_d[:, None]
        qdd[:, :, 0] -= tilt_dd[:, None]
        n = len(t)
        Lf = p.foot_length
        fy = np.zeros((n, 2))
        cop_x = np.zeros((n, 2))
        cop_z = np.zeros((n, 2))
        stance = np.zeros((n, 2), bool)
        a_p = np.zeros((n, 2))
        fx = np.zeros((n, 2))
        point = np.zeros((n, 2, 2))
        for s in range(2):
            cop_z[:, s] = self.cop_off + 0.004 * self.sway[s](t)
        if sp.duty < 1.0:
            W = self.Mc * G * self.load_style
            amp = (W / 2) / (sp.duty * self.shape_mean)
            for s in range(2):
                st = frac[:, s] < sp.duty
                sv = np.clip(frac[:, s] / sp.duty, 0.0, 1.0)
                stance[:, s] = st
                fy[:, s] = np.where(st, amp * self._shape(sv), 0.0)
                cop_x[:, s] = Lf * (sp.cop[0] + (sp.cop[1] - sp.cop[0]) * sv)
                cop_z[:, s] += 0.006 * np.sin(2 * np.pi * sv)
                point[:, s] = dyn.cop_point(p, q[:, s], cop_x[:, s])
                # GRF aimed at a point ahead of the hip early in stance (most in loading response),
                # behind it late
                # ... and, with a deeply flexed knee, toward the knee (the body's COM moves
                # forward over the foot; the line does not pass far behind a bent knee)
                knee_x = dyn.points(p, q[:, s])["knee"][:, 0]
                aim_x = (self.gait_offset * np.cos(np.pi * sv) + 0.035 * (1 - sv) ** 2
                         + 0.2 * np.sin(q[:, s, 1]) ** 2 * knee_x)
                fx[:, s] = np.clip(fy[:, s] * (aim_x - point[:, s, 0]) / (-point[:, s, 1]),
                                   -0.8 * fy[:, s], 0.8 * fy[:, s])  # friction cone
            a_p[:, 0] = fx.sum(1) / self.Mc
            a_p[:, 1] = fy.sum(1) / self.Mc - G
        else:
            # both feet down, sharing the load (a leg in an irregular event -- catching, twisting --
            # is lifted and hands its load to the other): the pelvis moves as the loaded legs
            # dictate (hip acceleration = minus the ankle's acceleration relative to the hip,
            # weighted by the load shares)
            w = self.shift(t)
            # a leg extended behind the body (hip extension, the trailing leg of a lunge) carries less
            lean_in = 1.0 + 0.8 * np.sin(q_rel[:, :, 0])
            b = np.stack([(1 + w) / 2, (1 - w) / 2], 1) * lean_in * (1.0 - 0.97 * self._lift)
            share = b / b.sum(1, keepdims=True)
            acc = np.zeros((n, 2))
            for s in range(2):
                th1 = q[:, s, 0]
                th2 = q[:, s, 0] - q[:, s, 1]
                d1, d2 = qd[:, s, 0], qd[:, s, 0] - qd[:, s, 1]
                dd1, dd2 = qdd[:, s, 0], qdd[:, s, 0] - qdd[:, s, 1]
                for th, d, dd, l in ((th1, d1, dd1, p.l1), (th2, d2, dd2, p.l2)):
                    u = np.stack([np.sin(th), -np.cos(th)], -1)
                    un = np.stack([np.cos(th), np.sin(th)], -1)
                    acc += share[:, s, None] * l * (dd[:, None] * un - (d * d)[:, None] * u)
            a_p = -acc
            load = 1.0
            if self.load_coef is not None:
                phi = self.phase(t)[0]
                load = self.load_coef[0] + fourier_eval(self.load_coef, phi)[0]
            Wt = self.Mc * (G + a_p[:, 1]) * load
            # the trunk and arms move against the pelvis: the body's COM takes about half of the
            # pelvis's horizontal acceleration, and that is what the feet must push for
            Wx = 0.5 * self.Mc * a_p[:, 0] * load
            for s in range(2):
                stance[:, s] = share[:, s] > 0.02
                fy[:, s] = np.maximum(Wt * share[:, s], 0.0)
                if sp.grf == "vertical":
                    # quasi-static balance: the CoP lies under the body's COM, which sits above the
                    # hip, moved forward as the trunk leans (pelvis tilt beyond neutral) and swaying;
                    # the foot bounds where it can be
                    ankle_x = dyn.points(p, q[:, s])["ankle"][:, 0]
                    com_x = 0.25 * np.sin(2 * (tilt - np.radians(self.tilt0))) + 0.01 * self.sway[s](t)
                    cop_x[:, s] = np.clip(com_x - ankle_x + p.heel_to_ankle, 0.05 * Lf, 0.95 * Lf)
                else:
                    cop_x[:, s] = Lf * (0.45 + 0.08 * self.sway[s](t))
                point[:, s] = dyn.cop_point(p, q[:, s], cop_x[:, s])
                if sp.grf == "vertical":
                    fx[:, s] = np.clip(Wx * share[:, s] + (self.lean(t) * fy[:, s] if self.lean is not None else 0.0),
                                       -0.8 * fy[:, s], 0.8 * fy[:, s])
                else:  # the force line aims near the hip (lunges: the trailing leg pushes along itself)
                    knee_x = dyn.points(p, q[:, s])["knee"][:, 0]
                    aim_x = 0.5 * np.sin(q[:, s, 1]) ** 2 * knee_x
                    fx[:, s] = np.clip(fy[:, s] * (aim_x - point[:, s, 0]) / (-point[:, s, 1]),
                                       -0.8 * fy[:, s], 0.8 * fy[:, s])  # friction cone
            if sp.grf != "vertical":
                a_p[:, 0] = fx.sum(1) / self.Mc
        g_eff = np.array([0.0, -G]) - a_p
        f = np.stack([fx, fy], axis=-1)
        tau = np.empty((n, 2, 2))
        for s in range(2):
            tau[:, s] = dyn.inverse_dynamics(p, q[:, s], qd[:, s], qdd[:, s], g_eff, f[:, s], point[:, s])
        return dict(t=t, q=q_rel, qd=qd_rel, qdd=qdd_rel, q_abs=q, qd_abs=qd, qdd_abs=qdd, tilt=tilt, tilt_d=tilt_d, tilt_dd=tilt_dd, fy=fy, fx=fx, f=f, point=point, cop_x=cop_x, cop_z=cop_z,
                    stance=stance, a_p=a_p, g_eff=g_eff, tau_tot=tau)

    def exo_command(self, t):
        """The exoskeleton's torque command (= recorded torque without bias/gain effects):
        a modulated share of the required torque, seen with the controller's lag, plus the
        controller's own variation, saturated at +-15 N m. (T, 2, 2)"""
        t = np.asarray(t, float)
        tau_l = self.core(t - self.exo_lag)["tau_tot"]
        out = np.empty_like(tau_l)
        for s in range(2):
            for j in range(2):
                g = self.exo_gain[j] * (1 + self.exo_mod[s][j](t))
                out[:, s, j] = soft_clip(g * tau_l[:, s, j] + self.exo_wiggle[s][j](t))
        return out

    def applied(self, t, cmd=None):
        """Exoskeleton torque acting on the limb: the command delayed by each joint's actuation
        delay (``cmd``: the command at t, reused where there is no delay)."""
        out = np.empty(np.shape(t) + (2, 2))
        done = {}
        for j in range(2):
            d = float(self.fx[j].get("actuation_delay", 0.0))
            if d not in done:
                done[d] = cmd if (d == 0.0 and cmd is not None) else self.exo_command(np.asarray(t) - d)
            out[:, :, j] = done[d][:, :, j]
        return out

    def evaluate(self, t):
        """All true and recorded quantities (noise-free) at times t."""
        c = self.core(t)
        cmd = self.exo_command(t)
        app = self.applied(t, cmd)
        qd = c["qd"]
        tau_h = c["tau_tot"] - app
        q_meas = c["q"].copy()
        qd_meas = qd.copy()
        rec = cmd.copy()
        for j in range(2):
            fx = self.fx[j]
            if "viscous_damping" in fx:
                tau_h[:, :, j] += fx["viscous_damping"] * qd[:, :, j]
            if "coulomb_friction" in fx:
                tau_h[:, :, j] += fx["coulomb_friction"] * np.tanh(qd[:, :, j] / COULOMB_EPS)
            if "stribeck_friction" in fx:
                Fs, vs = fx["stribeck_friction"]
                tau_h[:, :, j] += Fs * np.exp(-(qd[:, :, j] / vs) ** 2) * np.tanh(qd[:, :, j] / COULOMB_EPS)
            if "torque_gain" in fx:
                rec[:, :, j] = fx["torque_gain"] * rec[:, :, j]
            if "torque_bias" in fx:
                rec[:, :, j] = rec[:, :, j] + fx["torque_bias"]
            if "backlash" in fx:
                for s in range(2):
                    q_meas[:, s, j] = play(q_meas[:, s, j], fx["backlash"])
                    qd_meas[:, s, j] = np.gradient(q_meas[:, s, j], t)
            if "strap_compliance" in fx:
                k = fx["strap_compliance"]
                h = 1e-4
                dapp = (self.applied(t + h)[:, :, j] - self.applied(t - h)[:, :, j]) / (2 * h)
                q_meas[:, :, j] += app[:, :, j] / k
                qd_meas[:, :, j] += dapp / k
            if "encoder_offset" in fx:
                q_meas[:, :, j] += fx["encoder_offset"]
        c.update(tau_e_cmd=cmd, tau_e_app=app, tau_e_rec=rec, tau_h=tau_h, q_meas=q_meas, qd_meas=qd_meas)
        return c


def _lowpass(x, cutoff, axis=0):
    b, a = butter(2, cutoff / (FS / 2))
    return filtfilt(b, a, x, axis=axis)


def record(world: TrialWorld, seconds: float, rng: np.random.Generator, noise: bool = True):
    """Sample a trial at 200 Hz: returns (exo_columns, moment_columns, truth) where the first two
    are dicts column -> array in the CSV units of layout 1, and truth the evaluate() arrays."""
    n = int(round(seconds * FS))
    t = np.arange(n) * DT
    ev = world.evaluate(t)
    M = world.M
    exo, mom = {"time": t}, {"time": t}
    for s, side in enumerate(SIDES):
        for j, jn in enumerate(("hip", "knee")):
            ang = np.degrees(ev["q_meas"][:, s, j])
            if noise:
                ang = ang + rng.normal(0, ENC_NOISE_DEG, n)
                vel = _lowpass(np.gradient(ang, DT), VEL_CUTOFF_HZ)
            else:
                vel = np.degrees(ev["qd_meas"][:, s, j])
            exo[f"{jn}_angle_{side}"] = ang
            exo[f"{jn}_angle_{side}_velocity_filt"] = vel
    for s, side in enumerate(SIDES):
        fy = ev["fy"][:, s].copy()
        cx, cz = ev["cop_x"][:, s].copy(), ev["cop_z"][:, s].copy()
        if noise:
            on = fy > 0
            fy = np.where(on, np.maximum(fy * (1 + rng.normal(0, 0.02)) + rng.normal(0, FORCE_NOISE_N, n), 0.0), 0.0)
            cx = cx + rng.normal(0, COP_NOISE_M, n)
            cz = cz + rng.normal(0, COP_NOISE_M, n)
            undefined = fy < COP_MIN_FORCE
        else:
            undefined = fy <= 0
        cx[undefined] = np.nan
        cz[undefined] = np.nan
        exo[f"insole_{side}_force_y"] = fy
        exo[f"insole_{side}_cop_x"] = cx
        exo[f"insole_{side}_cop_z"] = cz
    for s, side in enumerate(SIDES):
        for j, jn in enumerate(("hip", "knee")):
            r = ev["tau_e_rec"][:, s, j]
            exo[f"{jn}_angle_{side}_torque_measured"] = r + (rng.normal(0, EXO_NOISE_NM, n) if noise else 0.0)
    for s, side in enumerate(SIDES):
        for j, col in enumerate((f"hip_flexion_{side}_moment", f"knee_angle_{side}_moment")):
            m = ev["tau_h"][:, s, j] / M
            if noise:
                e = _lowpass(rng.normal(0, 1, n), 8.0)
                m = m + MOMENT_NOISE * e / max(e.std(), 1e-12)
            mom[col] = m
    if noise and rng.random() < 0.1:
        # an occasional gap in the inverse-dynamics labels (markers occluded): NaN, to be masked
        i0 = int(rng.integers(0, max(n - 60, 1)))
        ln = int(rng.integers(20, 60))
        for k in list(mom):
            if k != "time":
                mom[k][i0:i0 + ln] = np.nan
    return exo, mom, ev
