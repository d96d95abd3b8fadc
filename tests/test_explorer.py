"""The browser explorer (scripts/explore_web.py): its JSON API on tiny scenes as a user chains
the scripts (explore.py's first-order error, simulate.py's targets), bad requests, 1 and 2
ranks, SIGINT, and the page in real headless Chromium."""

import json
import os
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from test_scripts import ROOT, _mpirun, _run

import scripts._launch as launch
from scripts._launch import chromium, explorer, request, set_params, wait_ready

#: The tests' tier (conftest.py): the explorer's server and scripts.
TIER = "scripts"

CASE = ["--case", "class3", "--resolution", "tiny"]
EXPLORE = [str(ROOT / "scripts" / "explore.py"), *CASE]
SIMULATE = [str(ROOT / "scripts" / "simulate.py"), *CASE]


def _python(script_args):
    import sys

    return [sys.executable, *script_args]


def _scene(url, synthetic=True):
    status, scene = launch.request(url + "api/scene")
    assert status == 200
    if synthetic:   # a synthetic head: its own frame
        assert np.allclose(scene["head_axes"], np.eye(3))
    status, raw = launch.request(url + "api/sensitivity")
    assert status == 200
    S = np.frombuffer(raw, dtype="<f4").reshape(len(scene["vertices"]), 3,
                                                 len(scene["param_names"]))
    return scene, S


def _dp(scene, p: dict) -> np.ndarray:
    """(Np,) p - p0 for the parameters ``p`` names (the others at p0)."""
    return np.array([p.get(n, p0) - p0 for n, p0 in zip(scene["param_names"], scene["p0"])])


def _first_order(scene, S, p: dict) -> np.ndarray:
    return np.asarray(scene["vertices"]) + S.astype(float) @ _dp(scene, p)


def _first_order_landmarks(scene, p: dict) -> dict:
    """{name: (3,)} the landmarks at p to first order, from /api/scene's."""
    S = np.asarray(scene["landmark_sensitivity"])
    return {n: np.asarray(x) + S[i] @ _dp(scene, p)
            for i, (n, x) in enumerate(scene["landmarks"].items())}


@pytest.mark.parametrize("contact", ["glued", "sliding"])
def test_solve_matches_the_first_order_error_explore_py_measures(tmp_path, contact):
    """After a 1 mm move, /api/solve's skin is x0 + S dp (from /api/scene and
    /api/sensitivity) within the first-order error that explore.py --compare measures for
    the same move, its reported maximum is that distance, and its landmarks are
    simulate.py's; with the lips glued to the teeth (the synthetic default) and sliding."""
    opt = ["--contact", contact]
    rep = tmp_path / "explore.json"
    r = _run(_python(EXPLORE + opt + ["--dp", "mandible.advance_mm=1", "--compare",
                                      "--report", str(rep)]))
    assert r.returncode == 0, r.stderr[-2000:]
    measured = json.loads(rep.read_text())["predictions"][0]["plain_error_max_mm"]
    sim = tmp_path / "sim.json"
    r = _run(_python(SIMULATE + opt + ["--p", "mandible.advance_mm=1", "--report", str(sim)]))
    assert r.returncode == 0, r.stderr[-2000:]
    with explorer(CASE + opt) as (url, proc):
        scene, S = _scene(url)
        status, out = request(url + "api/solve", {"p": {"mandible.advance_mm": 1.0}})
        assert status == 200, out
    assert proc.returncode == 0
    err = np.linalg.norm(np.asarray(out["vertices"]) - _first_order(
        scene, S, {"mandible.advance_mm": 1.0}), axis=1).max()
    assert 0.0 < err <= measured + 1e-4
    assert err == pytest.approx(measured, rel=0.02, abs=1e-4)
    assert out["first_order_error_max_mm"] == pytest.approx(err, abs=1e-4)  # float32 S
    assert out["iterations"] > 0 and out["seconds"] > 0
    for name, x in json.loads(sim.read_text())["landmarks"].items():
        np.testing.assert_allclose(out["landmarks"][name], x, atol=1e-6)


BAD = [
    ("api/solve", b'{"p": {"mandible.advance_mm": NaN}}', "not a number"),
    ("api/solve", b'{"p": {"mandible.advance_mm": Infinity}}', "not a number"),
    ("api/solve", b'{"p": {"nose.length_mm": 1}}', "unknown parameter"),
    ("api/solve", b'{"p": {"mandible.advance_mm": 40}}', "outside its feasible range"),
    ("api/solve", b'{"p": {"mandible.advance_mm": "5"}}', "finite number"),
    ("api/solve", b'{"p": {"mandible.advance_mm": true}}', "finite number"),
    ("api/solve", b'{"p": [1, 2]}', "must be an object"),
    ("api/solve", b'{"p": {"mandible.advance_mm": 1}, "path": "/etc/passwd"}', "unknown key"),
    ("api/solve", b'{"p": ', "malformed JSON"),
    ("api/solve", b'[1]', "JSON object"),
    ("api/solve", b'\xff\xfe', "malformed JSON"),
    ("api/corrected", b'{"p": {"mandible.advance_mm": -1e309}}', "finite number"),
    ("api/relinearise", b'{"p": {"maxilla.yaw_deg": 11}}', "outside its feasible range"),
    ("api/match", b'{"p": {"jaws.advance_mm": 1}}', "unknown parameter"),
    ("api/export", b'{"p": 3}', "must be an object"),
    ("api/plan", b'{"targets": {"Pg": [0, 1]}}', "[x, y, z]"),
    ("api/plan", b'{"targets": {"Nose": [0, 1, 2]}}', "unknown landmark"),
    ("api/plan", b'{"targets": {"Pg": [0, 1e6, 0]}}', "mm from its rest position"),
    ("api/plan", b'{"targets": {}}', "must be an object"),
    ("api/plan", b'{"occlusion": "open"}', "'occlusion' must be one of"),
    ("api/plan", b'{"ftol": 0}', "ftol must be"),
    ("api/plan", b'{"max_iterations": 1e9}', "max_iterations must be"),
]


def test_bad_requests_get_400_and_the_server_still_answers():
    """Every bad input gets 400 {"error": ...} (one line, no traceback); unknown paths 404
    in JSON; the server answers after each, and SIGINT stops it with exit code 0."""
    with explorer(CASE) as (url, proc):
        for path, body, match in BAD:
            status, out = request(url + path, raw=body)
            assert status == 400, (path, body, out)
            assert match in out["error"] and "Traceback" not in out["error"], out
            assert "\n" not in out["error"]
        status, out = request(url + "api/nothing")
        assert status == 404 and "error" in out
        status, out = request(url + "api/solve", {"p": {"mandible.advance_mm": 0.5}})
        assert status == 200
    assert proc.returncode == 0, proc.stderr.read()[-2000:]


def test_plan_to_simulate_py_targets_recovers_the_treatment(tmp_path):
    """Targets written by simulate.py at p* (final occlusion, jaws.* motions), planned by
    /api/plan from p = 0 with α = 0: p* recovered (1e-3) and the targets reached (0.01 mm);
    the progress lists every Gauss-Newton iteration; a request during the plan gets 503;
    the explorer is re-linearised at the plan; Export's transforms keep the occlusion;
    /api/match of a predicted face finds parameters whose true face is that close."""
    p_star = {"jaws.advance_mm": 2.0, "jaws.pitch_deg": -1.5, "jaws.yaw_deg": 1.0}
    sim = tmp_path / "sim.json"
    r = _run(_python(SIMULATE + ["--occlusion", "final", "--params-used",
                                 ",".join(f"jaws.{m}" for m in ("advance_mm", "lateral_mm",
                                          "vertical_mm", "pitch_deg", "roll_deg",
                                          "yaw_deg")),
                                 "--p", *[f"{k}={v}" for k, v in p_star.items()],
                                 "--report", str(sim)]))
    assert r.returncode == 0, r.stderr[-2000:]
    targets = json.loads(sim.read_text())["landmarks"]
    with explorer(CASE + ["--occlusion", "final"]) as (url, proc):
        busy = {}

        def meanwhile():
            time.sleep(0.3)
            busy["status"] = request(url + "api/solve", {"p": {}})[0]
        t = threading.Thread(target=meanwhile)
        t.start()
        status, plan = request(url + "api/plan", {"targets": targets, "occlusion": "final",
                                                  "tikhonov": 0, "ftol": 1e-9})
        t.join()
        assert status == 200, plan
        assert busy["status"] == 503
        found = dict(zip(plan["param_names"], plan["params_optimal"]))
        for name, v in found.items():
            assert v == pytest.approx(p_star.get(name, 0.0), abs=1e-3), name
        assert plan["mean_distance_after_mm"] < 0.01
        status, progress = request(url + "api/progress")
        assert progress["running"] is None
        assert len(progress["history"]) == plan["gn_iterations"] + 1
        scene, S = _scene(url)
        np.testing.assert_allclose(scene["p0"], plan["params_optimal"], atol=1e-12)
        status, out = request(url + "api/export", {"p": found})
        assert status == 200
        T = {s: np.asarray(m) for s, m in out["transforms"].items()}
        np.testing.assert_allclose(np.linalg.inv(T["maxilla_L"]) @ T["mandible"],
                                   out["occlusion"], atol=1e-9)
        asked = dict(found, **{"jaws.advance_mm": found["jaws.advance_mm"] + 0.5})
        status, match = request(url + "api/match", {"p": asked})
        assert status == 200, match
        assert match["distance_max_mm"] < 0.05
        assert match["p"]["jaws.advance_mm"] == pytest.approx(asked["jaws.advance_mm"],
                                                              abs=0.05)
        status, plan = request(url + "api/plan", {"targets": targets, "occlusion": "free"})
        assert status == 200 and plan["param_names"][0].startswith("mandible.")
        assert plan["mean_distance_after_mm"] < plan["mean_distance_before_mm"]
    assert proc.returncode == 0


def test_explores_a_plan_py_report(tmp_path):
    """plan.py's report opens in the explorer (the README's `make explore`): its occlusion,
    parameters, planned p as p0 and its targets, and the skin there is the planned one."""
    rep, out = tmp_path / "plan.json", tmp_path / "plan"
    r = _run(_python([str(ROOT / "scripts" / "plan.py"), *CASE, "--occlusion", "final",
                      "--out", str(out), "--report", str(rep)]))
    assert r.returncode == 0, r.stderr[-2000:]
    plan = json.loads(rep.read_text())
    with explorer(["--plan-report", str(rep)]) as (url, proc):
        scene, S = _scene(url)
    assert proc.returncode == 0
    assert scene["occlusion"] == "final" and scene["param_names"] == plan["param_names"]
    np.testing.assert_allclose(scene["p0"], plan["params_optimal"], atol=1e-12)
    for name, row in plan["landmarks"].items():
        np.testing.assert_allclose(scene["targets"][name], row["target"], atol=1e-12)
        np.testing.assert_allclose(scene["landmarks"][name], row["after"], atol=1e-3)
        # the band the page shows at the plan is the plan's own (issue 46)
        assert scene["band"]["landmarks"][name] == pytest.approx(
            plan["bands"]["landmarks"][name]["r95_mm"], rel=0.01, abs=1e-4)
    assert max(scene["band"]["r95_mm"]) > 0


@pytest.mark.mpi
def test_same_answers_on_1_and_2_ranks():
    """Under mpirun -n 2 rank 0 serves and every rank solves: the scene, a solve and a
    corrected prediction are those of one rank."""
    answers = {}
    for n in (1, 2):
        with explorer(CASE, mpirun=_mpirun(n) if n > 1 else ()) as (url, proc):
            scene, S = _scene(url)
            p = {"mandible.advance_mm": 2.0, "maxilla.yaw_deg": 1.0}
            answers[n] = (scene, S, request(url + "api/solve", {"p": p})[1],
                          request(url + "api/corrected", {"p": p})[1])
        assert proc.returncode == 0, proc.stderr.read()[-2000:]
    (s1, S1, a1, c1), (s2, S2, a2, c2) = answers[1], answers[2]
    assert s1["triangles"] == s2["triangles"] and s1["param_names"] == s2["param_names"]
    np.testing.assert_allclose(s2["vertices"], s1["vertices"], atol=1e-6)
    np.testing.assert_allclose(S2, S1, atol=1e-5)
    np.testing.assert_allclose(a2["vertices"], a1["vertices"], atol=1e-5)
    np.testing.assert_allclose(c2["vertices"], c1["vertices"], atol=1e-4)


def _bone_at(scene, transforms) -> np.ndarray:
    """The bone's vertices (B, 3) moved by each segment's 4×4 (in the scene's order)."""
    b = scene["bone"]
    x = np.asarray(b["vertices"])
    out = x.copy()
    for k, A in enumerate(np.asarray(T) for T in transforms):
        on = np.asarray(b["segment"]) == k
        out[on] = x[on] @ A[:3, :3].T + A[:3, 3]
    return out


def _first_order_bone(scene, p: dict) -> np.ndarray:
    """The bone's vertices (B, 3) at p to first order: each segment's T0 + dT dp."""
    b, dp = scene["bone"], _dp(scene, p)
    return _bone_at(scene, [np.asarray(T0) + np.tensordot(dp, np.asarray(dT), axes=1)
                            for T0, dT in zip(b["transforms"], b["transform_derivatives"])])


@pytest.fixture(scope="module")
def cranium_scene(tmp_path_factory):
    """Cranium.inv3 (Debian's invesalius-examples) through ct_scene.py at coarse: the mesh
    (its report beside it, ``ct.json``)."""
    from test_ct import CRANIUM, CT_SCENE, EXAMPLES

    if not CRANIUM.exists():
        pytest.skip(f"{CRANIUM} is absent (Debian's invesalius-examples; `make test` "
                    "installs it)")
    out = tmp_path_factory.mktemp("cranium")
    r = _run(CT_SCENE + ["--ct", str(CRANIUM), "--osteotomies", str(EXAMPLES / "cranium.json"),
                         "--resolution", "coarse", "--out", str(out), "--report",
                         str(out / "ct.json")],
             env=dict(os.environ, ORTHODIFF_CACHE=str(out / "cache")))
    assert r.returncode == 0, r.stderr[-2000:]
    return out / "scene.vtu"


@pytest.mark.browser
@pytest.mark.parametrize("which", ["synthetic", pytest.param("cranium", marks=pytest.mark.cgal)])
def test_the_page_in_headless_chromium(request, tmp_path, which):
    """Real Chromium (SwiftShader WebGL), on the synthetic head and on the Cranium CT's
    scene: the page loads in a skin tone; a slider move draws x0 + S dp (1e-3 mm of the
    API's); the bone toggle shows the segments moved by their first-order motion under a
    see-through skin; Solve shows the first-order error map with the API's maximum, and the
    bone by the segments' exact motions at p (the answer's); the console has no error. Saves
    the skin and the bone (ORTHODIFF_SCREENSHOT or tmp, per scene). On Cranium, with a
    target held along the head's anterior axis only (Sn) and one held along every axis
    (Prn), the landmark table gives each distance along the axes its target holds."""
    shot = Path(os.environ.get("ORTHODIFF_SCREENSHOT", tmp_path / "explorer.png"))
    shot = shot if which == "synthetic" else shot.with_name(f"{shot.stem}_{which}.png")
    if which == "synthetic":
        args, p = CASE, {"mandible.advance_mm": 3.0, "mandible.yaw_deg": -2.0}
    else:
        mesh = request.getfixturevalue("cranium_scene")
        ct = json.loads(mesh.with_name("ct.json").read_text())
        anterior = np.asarray(ct["head_frame"])[:3, 1]
        rest = {k: np.asarray(ct["landmarks"][k]) for k in ("Sn", "Prn")}
        targets = {"Sn": {"at": (rest["Sn"] + 3 * anterior + [0, 0, 5]).tolist(),
                          "along": ["anterior"]}, "Prn": (rest["Prn"] + [1, 1, 0]).tolist()}
        (tmp_path / "targets.json").write_text(json.dumps(targets))
        args = ["--mesh", str(mesh), "--targets", str(tmp_path / "targets.json"),
                "--params-used", "maxilla.advance_mm,maxilla.vertical_mm,maxilla.pitch_deg"]
        p = {"maxilla.advance_mm": 3.0, "maxilla.pitch_deg": 2.0}
    with explorer(args) as (url, proc):
        scene, S = _scene(url, synthetic=which == "synthetic")
        driver = chromium()
        try:
            driver.get(url)
            wait_ready(driver)
            loaded = driver.execute_script("return performance.getEntriesByType('resource')"
                                           ".map(e => e.name)")
            assert loaded and all(u.startswith(url) for u in loaded), loaded   # no CDN
            assert driver.find_element("id", "colour").get_attribute("value") == "skin"
            assert not driver.find_element("id", "legend").is_displayed()
            frame_ms = set_params(driver, p)
            assert frame_ms > 0
            drawn = np.asarray(driver.execute_script(
                "return Array.from(window.explorer.skinPositions())")).reshape(-1, 3)
            np.testing.assert_allclose(drawn, _first_order(scene, S, p), atol=1e-3)
            if which == "cranium":
                cells = [row.text.split() for row in driver.find_elements(
                    "css selector", "#landmarks tbody tr")]
                table = {c[0]: c[1] for c in cells}
                band = {c[0]: float(c[2]) for c in cells}   # issue 46: the band at p0
                assert all(band[n] == pytest.approx(scene["band"]["landmarks"][n], abs=0.006)
                           for n in band), band
                now = _first_order_landmarks(scene, p)
                assert scene["targets"] == targets and set(table) == set(targets), table
                assert float(table["Sn"]) == pytest.approx(
                    abs((now["Sn"] - targets["Sn"]["at"]) @ anterior), abs=0.006), table
                assert float(table["Prn"]) == pytest.approx(
                    np.linalg.norm(now["Prn"] - targets["Prn"]), abs=0.006), table
            # the band map (issue 46): its legend tops at the widest band of a skin vertex,
            # none at rest (p0 = 0: nothing moves, whatever the tissue)
            driver.execute_script("const c = document.getElementById('colour');"
                                  "c.value = 'band'; c.onchange();")
            t0 = time.monotonic()
            while not driver.find_element("id", "legend").is_displayed():
                assert time.monotonic() - t0 < 10
                time.sleep(0.05)
            top = float(driver.find_element("id", "legend-hi").text)
            assert top == pytest.approx(max(scene["band"]["r95_mm"]), abs=0.006)
            assert (top > 0) == any(scene["p0"]), (top, scene["p0"])
            driver.execute_script("const c = document.getElementById('colour');"
                                  "c.value = 'skin'; c.onchange();")
            shot.parent.mkdir(parents=True, exist_ok=True)
            driver.save_screenshot(str(shot))
            assert driver.execute_script("return window.explorer.bonePositions()") is None
            driver.execute_script("return window.explorer.showBone(true)")
            bone = np.asarray(driver.execute_script(
                "return Array.from(window.explorer.bonePositions())")).reshape(-1, 3)
            np.testing.assert_allclose(bone, _first_order_bone(scene, p), atol=1e-3)
            moved = np.linalg.norm(bone - np.asarray(scene["bone"]["vertices"]), axis=1)
            still = np.asarray(scene["bone"]["segment"]) < 0   # the skull and the free bone
            assert moved.max() > 2.0 and still.mean() > 0.1 and moved[still].max() < 1e-4
            assert driver.execute_script("return window.explorer.skinOpacity()") < 1
            driver.save_screenshot(str(shot.with_name(shot.stem + "_bone.png")))
            driver.execute_script("return window.explorer.showBone(false)")
            driver.find_element("id", "solve").click()
            t0 = time.monotonic()
            while "first-order error max" not in driver.find_element("id", "status").text:
                assert time.monotonic() - t0 < 60, driver.find_element("id", "status").text
                time.sleep(0.05)
            legend = driver.find_element("id", "legend-title").text
            assert "first-order error" in legend
            shown_max = driver.execute_script("return window.explorer.errorMapMax()")
            status, out = launch.request(url + "api/solve", {"p": p})
            assert shown_max == pytest.approx(out["first_order_error_max_mm"], abs=1e-3)
            driver.execute_script("return window.explorer.showBone(true)")
            bone = np.asarray(driver.execute_script(
                "return Array.from(window.explorer.bonePositions())")).reshape(-1, 3)
            np.testing.assert_allclose(bone, _bone_at(scene, out["transforms"]), atol=1e-3)
            errors = [e for e in driver.get_log("browser") if e["level"] == "SEVERE"]
            assert not errors, errors
            assert driver.execute_script("return window.explorer.lastError") is None
        finally:
            driver.quit()
    assert proc.returncode == 0
