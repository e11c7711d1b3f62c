"""The objects' own fit of ``benchmarks/studies/real_objects_oracle.py`` on objects rendered by its form."""

import importlib.util
from pathlib import Path

import numpy as np

STUDY = Path(__file__).resolve().parents[1] / "benchmarks" / "studies" / "real_objects_oracle.py"


def load_study():
    spec = importlib.util.spec_from_file_location("real_objects_oracle", STUDY)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def rendered_objects(rng, eta=(0.4, 0.1, 0.05), veil=(0.02, 0.05, 0.08), beta=(0.3, 0.3, 0.3)):
    """Four objects of fixed albedo seen at ranges 0.5-3 m through the form, with no gains per frame."""
    eta, veil_b, beta = (np.array(v) for v in (eta, veil, beta))
    objects = {}
    for name, albedo in {"white": (0.8, 0.8, 0.8), "red": (0.6, 0.1, 0.1), "cyan": (0.1, 0.5, 0.6),
                         "grey": (0.3, 0.3, 0.3)}.items():
        r = rng.uniform(0.5, 3.0, 12)
        rgb = np.array(albedo) * np.exp(-eta * r[:, None]) + veil_b * -np.expm1(-beta * r[:, None])
        objects[name] = {"frames": [f"f{k:02d}" for k in range(12)], "range_m": r.tolist(),
                         "mean_linear_rgb": rgb.tolist()}
    return objects


def test_the_objects_fit_undoes_its_own_form_and_a_wrong_water_does_not():
    study = load_study()
    rows = study.ObjectRows(rendered_objects(np.random.default_rng(0)))
    raw = rows.spreads(rows.rgb)
    everything = np.ones(len(rows.obj), bool)
    water, _ = study.fit_form(rows, everything, gains=False)
    np.testing.assert_allclose(water[:, 0], [0.4, 0.1, 0.05], atol=0.02)
    J = np.zeros_like(rows.rgb)
    study.correct(rows, water, np.zeros((len(rows.frames), 3)), everything, J)
    fitted = rows.spreads(J)
    assert all(fitted[o] < 0.05 * raw[o] for o in raw)
    clear = np.array([[0.0, 0.0, 1e-3]] * 3)  # no attenuation, no veil: the raw colours back
    study.correct(rows, clear, np.zeros((len(rows.frames), 3)), everything, J)
    assert rows.spreads(J) == raw
