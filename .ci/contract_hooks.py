"""Schemathesis hooks: the rules of POST /infer and /log_prob that JSON Schema cannot state.

openapi.yaml states them in words (VelocityCurve, ImpedanceCurve, Values, the query
parameters' "text/csv bodies only", LogProbRequest.theta); JSON Schema cannot express
arrays of equal length, frequencies that increase and cover a band, or a row as wide as
the model. Each generated case of those two operations is made to follow them, keeping
what was generated where the rules leave a choice: which measures, how many points, the
units, the optional fields and the query. Values come from a typical ear (the contract's
own JSON example) moved by amounts drawn from the generated data, within a human ear's
range. A case so made is valid by the contract, so the server must accept it
(`positive_data_acceptance`).

Loaded by `.ci/run` with SCHEMATHESIS_HOOKS=contract_hooks (PYTHONPATH=.ci).
"""

import csv
import hashlib
import io
import json
import math
import os
import random
import urllib.request

import schemathesis
import yaml

HERE = os.path.dirname(os.path.abspath(__file__))
BASE = os.environ.get("OTOFIT_BASE_URL", "http://127.0.0.1:18091")

with open(os.path.join(HERE, "..", "openapi.yaml"), encoding="utf-8") as f:
    SPEC = yaml.safe_load(f)
EXAMPLE = SPEC["paths"]["/infer"]["post"]["requestBody"]["content"]["application/json"]["example"]["measurements"]
UNITS = {
    name: SPEC["components"]["schemas"][name]["properties"]["magnitude_unit"]["enum"]
    for name in ("VelocityCurve", "ImpedanceCurve")
}
PHASE_UNITS = {"rad": 1.0, "deg": math.pi / 180.0, "cycles": 2 * math.pi}
# Factor from the SI unit to each unit (SI value / factor = value in the unit).
VELOCITY_FACTOR = {"m/s/Pa": 1.0, "SI": 1.0, "mm/s/Pa": 1e-3}
IMPEDANCE_FACTOR = {"MOhm": 1e6, "MΩ": 1e6, "cgs": 1e5, "dyn·s/cm⁵": 1e5, "dyn*s/cm^5": 1e5}

_BOXES = None


def boxes():
    """The default model's parameter boxes (name, low, high, log scale), read once."""
    global _BOXES
    if _BOXES is None:
        with urllib.request.urlopen(f"{BASE}/models/default", timeout=30) as r:
            params = json.load(r)["parameters"]
        _BOXES = [(p["low"], p["high"], p.get("scale") == "log10") for p in params]
    return _BOXES


def rng_of(case):
    """A generator seeded by the generated case, so a case maps to one valid case."""
    text = repr((case.body, case.query, case.media_type)).encode()
    return random.Random(hashlib.sha256(text).hexdigest())


def interp(f, xs, ys):
    """Linear interpolation in log-frequency, held flat outside the example's band."""
    lf = [math.log(x) for x in xs]
    t = min(max(math.log(f), lf[0]), lf[-1])
    for i in range(1, len(lf)):
        if t <= lf[i]:
            w = (t - lf[i - 1]) / (lf[i] - lf[i - 1])
            return ys[i - 1] + w * (ys[i] - ys[i - 1])
    return ys[-1]


def grid(rng, generated):
    """Increasing frequencies over the whole band, no gap over half an octave: as many
    points as were generated, at least 16 (6 octaves / 15 gaps < 0.5) and at most 200."""
    n = min(max(len(generated) if isinstance(generated, list) else 0, 16), 200)
    lo, hi = rng.uniform(150.0, 200.0), rng.uniform(8000.0, 10000.0)
    return [lo * (hi / lo) ** (i / (n - 1)) for i in range(n)]


def curve(rng, name, given, shift):
    """One magnitude/phase measure on a fresh grid, in the units generated (or a valid
    one), moved from the typical ear by the shift drawn for this case."""
    ex = EXAMPLE[name if name != "umbo_velocity" else "stapes_velocity"]
    fs = grid(rng, given.get("frequencies_hz"))
    kind = "ImpedanceCurve" if name == "impedance" else "VelocityCurve"
    unit = given.get("magnitude_unit")
    if unit not in UNITS[kind]:
        unit = rng.choice(UNITS[kind])
    phase_unit = given.get("phase_unit")
    if phase_unit not in PHASE_UNITS:
        phase_unit = rng.choice(list(PHASE_UNITS))
    log_mag = [math.log10(m) for m in ex["magnitude"]]
    out = {"frequencies_hz": fs, "magnitude": [], "phase": [], "magnitude_unit": unit, "phase_unit": phase_unit}
    for f in fs:
        m = 10 ** (interp(f, ex["frequencies_hz"], log_mag) + shift[0] + rng.uniform(-0.05, 0.05))
        p = interp(f, ex["frequencies_hz"], ex["phase"]) + shift[1] + rng.uniform(-0.05, 0.05)
        if name == "impedance":
            value = m / IMPEDANCE_FACTOR.get(unit, 1.0)
        elif unit.startswith("dB"):
            value = 20 * math.log10(m / 1e-3)
        else:
            value = m / VELOCITY_FACTOR[unit]
        out["magnitude"].append(value)
        out["phase"].append(p / PHASE_UNITS[phase_unit])
    return out


def absorbance(rng, given, shift):
    ex = EXAMPLE["absorbance"]
    fs = grid(rng, given.get("frequencies_hz"))
    values = [
        min(max(interp(f, ex["frequencies_hz"], ex["values"]) + shift + rng.uniform(-0.02, 0.02), 0.0), 1.0) for f in fs
    ]
    return {"frequencies_hz": fs, "values": values}


def measurements(rng, generated):
    """The measures generated (at least one), each made valid. Impedance and absorbance
    move together (both from the same ear), so they agree as the server checks."""
    names = [k for k in ("stapes_velocity", "impedance", "absorbance", "umbo_velocity") if k in (generated or {})]
    if not names:
        names = [rng.choice(["stapes_velocity", "impedance", "absorbance"])]
    out = {}
    for name in names:
        given = generated.get(name) if isinstance(generated, dict) else None
        given = given if isinstance(given, dict) else {}
        if name == "absorbance":
            out[name] = absorbance(rng, given, rng.uniform(-0.05, 0.05))
        else:
            shift = (rng.uniform(-0.3, 0.3), rng.uniform(-0.2, 0.2))
            out[name] = curve(rng, name, given, shift)
    return out


def theta_rows(rng, generated):
    """As many rows as generated, each as wide as the model and inside its box."""
    rows = len(generated) if isinstance(generated, list) and generated else 1
    out = []
    for _ in range(rows):
        row = []
        for lo, hi, log in boxes():
            q = rng.uniform(0.05, 0.95)
            row.append(lo * (hi / lo) ** q if log else lo + q * (hi - lo))
        out.append(row)
    return out


def table(rng):
    """A long-layout CSV table of one ear: frequency, absorbance and impedance, units in
    the header."""
    m = measurements(rng, {"absorbance": {}, "impedance": {"magnitude_unit": "cgs", "phase_unit": "deg"}})
    a, z = m["absorbance"], m["impedance"]
    text = io.StringIO()
    w = csv.writer(text, lineterminator="\n")
    w.writerow(["Frequency [Hz]", "Absorbance", "Zmag [cgs]", "Zang [deg]"])
    for i, f in enumerate(a["frequencies_hz"]):
        zf = interp(f, z["frequencies_hz"], z["magnitude"])
        zp = interp(f, z["frequencies_hz"], z["phase"])
        w.writerow([f"{f:.2f}", f"{a['values'][i]:.5f}", f"{zf:.5g}", f"{zp:.3f}"])
    return text.getvalue()


def valid(case):
    path = case.operation.path
    if path not in ("/infer", "/log_prob"):
        return case
    rng = rng_of(case)
    if case.media_type == "text/csv":
        # The table's own header names the columns and their units: `unit` and `select`
        # (which name columns of a table) are left out.
        case.body = table(rng)
        if case.query:
            case.query = {k: v for k, v in case.query.items() if k not in ("unit", "select")}
        return case
    # JSON: the query takes only `plot` ("text/csv bodies only" for the others).
    if case.query:
        case.query = {k: v for k, v in case.query.items() if k == "plot"}
    body = dict(case.body) if isinstance(case.body, dict) else {}
    # A generated id almost never names a model (a 404, accepted); half of those name the
    # default model instead, so that most cases reach the inference.
    if "model" in body and rng.random() < 0.5:
        body["model"] = "default"
    body["measurements"] = measurements(rng, body.get("measurements"))
    if path == "/log_prob":
        body["theta"] = theta_rows(rng, body.get("theta"))
    case.body = body
    return case


@schemathesis.hook
def before_generate_case(context, strategy):
    return strategy.map(valid)
