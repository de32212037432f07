"""docs/results.md states what its JSONs hold. Every table row of the page that names a JSON under docs/results/
is listed here with a rule that recomputes, from that JSON, each figure of the row's measured columns; the test
finds the row, looks for every recomputed figure in those columns, and fails on a number there that no rule
accounts for (a figure typed by hand, or one a re-run left behind). Numbers that are inputs rather than
results (a terrain's height, a paper's constant, the rounding threshold a claim names) are listed as given."""
import json
import os
import re
import sys
from functools import lru_cache

import numpy as np
import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PAGE = os.path.join(ROOT, "docs", "results.md")
RESULTS = os.path.join(ROOT, "docs", "results")


@lru_cache(maxsize=None)
def js(name):
    with open(os.path.join(RESULTS, name), encoding="utf-8") as f:
        return json.load(f)


def f1(x):
    return f"{x:.1f}"


def pct(rate, nd=1):
    return f"{100 * rate:.{nd}f}"


def sg(x):
    return f"{x:+.1f}"


def ci(lo, hi):
    return f"({sg(lo)} .. {sg(hi)})"


def diff(comp):
    """'+d points (lo .. hi)' of a paired comparison [d, lo, hi] (points)."""
    d, lo, hi = comp
    return f"{sg(d)} points {ci(lo, hi)}"


def neg(comp):
    """The comparison the other way round: B - A from A - B."""
    d, lo, hi = comp
    return [-d, -hi, -lo]


def _is_row(line):
    return line.startswith("|") and line.rstrip().endswith("|")


def row_of(key):
    lines = [ln for ln in open(PAGE, encoding="utf-8").read().splitlines() if _is_row(ln) and key in ln]
    assert len(lines) == 1, f"docs/results.md: {len(lines)} table rows hold {key!r}, want 1"
    return [c.strip() for c in re.split(r"(?<!\\)\|", lines[0].strip().strip("|"))]  # "\\|" is a pipe in a cell


# ---- Luneckas 2020 -------------------------------------------------------------------------------------------

L = "luneckas2020_h100_warp_n1024.json"


def _lrows(dist):
    return [r for r in js(L)["summary"]["rows"] if r["distance"] == dist]


def lu_flat():
    c = js(L)["calibration"]
    assert all(c[g][d]["abs_dalpha_deg"] < 0.5 for g in c for d in c[g])  # "no heading drift"
    return [f"tripod {f1(c['tripod']['1m']['goal_error_cm'])} / {f1(c['tripod']['2m']['goal_error_cm'])} cm",
            f"wave {f1(c['wave']['1m']['goal_error_cm'])} / {f1(c['wave']['2m']['goal_error_cm'])} cm"]


def lu_stuck():
    b = js(L)["summary"]["error_breakdown_pct"]
    cells = js(L)["cells"]
    assert all(cells[g][c][d][m]["abs_dx_cm"] > cells[g][c][d][m]["abs_dy_cm"]
               for g in cells for c in cells[g] for d in cells[g][c] for m in cells[g][c][d])
    return [f"{pct(b['without']['share_stuck'], 0)} % of runs stuck without the method",
            f"{pct(b['with']['share_stuck'], 0)} % with it"]


def lu_rel():
    s = js(L)["summary"]
    out = [f"All {s['cells_compared']} cells: {f1(s['overall_rel_error_without_pct'])} % -> "
           f"{f1(s['overall_rel_error_with_pct'])} %",
           f"{f1(s['low_density_1m_rel_error_without_pct'])} % -> {f1(s['low_density_1m_rel_error_with_pct'])} %"]
    for cat in ("low-small", "low-large", "high-small", "high-large"):
        rs = [r for r in _lrows("1m") if r["category"] == cat]
        out.append(f"{cat} {f1(np.mean([r['rel_error_without_pct'] for r in rs]))} -> "
                   f"{f1(np.mean([r['rel_error_with_pct'] for r in rs]))} %")
    return out


def lu_lower():
    s = js(L)["summary"]
    return [f"in {s['cells_with_lower']} of {s['cells_compared']} cells"]


def lu_fig20():
    out = []
    for dist, m in (("1m", 1.0), ("2m", 2.0)):
        e = [r["rel_error_with_pct"] * m for r in _lrows(dist)]  # per cent of the distance -> cm
        out.append(f"{f1(min(e))}-{f1(max(e))} cm at {dist[0]} m")
    return out


def lu_wave():
    return [js(L)["summary"]["wave_better_than_tripod_cells"]]


def lu_model():
    m = js(L)["model"]
    dls = [m[g][d][k]["dL_cm"] for g in m for d in m[g] for k in m[g][d]]

    def cell(g, d, k, c):
        x = m[g][d][k]["cells"][c]
        return f"{f1(x['model_abs_dx_cm'])} / {f1(x['sim_abs_dx_cm'])} cm"
    heads = [(x["model_abs_dalpha_deg"], x["sim_abs_dalpha_deg"])
             for g in m for d in m[g] for k in m[g][d] for x in m[g][d][k]["cells"].values()]
    mod, sim = zip(*heads)
    return [f"({min(dls):.2f}-{max(dls):.2f} cm per leg-obstacle interaction)",
            f"low-small {cell('wave', '1m', 'with', 'low-small')}",
            f"high-large {cell('tripod', '1m', 'without', 'high-large')}",
            f"low-large 2 m with {cell('wave', '2m', 'with', 'low-large')} (wave)",
            f"model {min(mod):.0f}-{max(mod):.0f} deg against {min(sim):.0f}-{max(sim):.0f} deg simulated"]


def lu_breakdown(method):
    b = js(L)["summary"]["error_breakdown_pct"][method]
    clean = 1.0 - b["share_stuck"] - b["share_torso_struck"]
    total = js(L)["summary"][f"overall_rel_error_{method}_pct"]
    assert abs(b["stuck"] + b["torso_struck"] + b["clean"] - total) < 1e-6  # the split is exact
    return [f"{f1(b['stuck'])} pts ({pct(b['share_stuck'], 0)} %",
            f"{f1(b['torso_struck'])} pts ({pct(b['share_torso_struck'], 0)} %)",
            f"{f1(b['clean'])} pts ({pct(clean, 0)} %)", f"{f1(total)} %"]


def lu_predictor():
    h = js("luneckas2020_predictor_cpu_n16.json")["held_out"]
    a, q = h["all_steps"], h["by_progress"]["75%"]
    return [f"on {h['sequences']} held-out walks", f"LSTM {f1(a['lstm_rms_cm'])} cm",
            f"last error carried forward {f1(a['last_error_rms_cm'])} cm", f"{f1(a['analytic_rms_cm'])} cm.",
            f"{f1(q['lstm_rms_cm'])} / {f1(q['last_error_rms_cm'])} / {f1(q['analytic_rms_cm'])} cm"]


# ---- Yu 2019 -------------------------------------------------------------------------------------------------

S, D, E = "yu2019_step_h100_warp_b1024.json", "yu2019_ditch_h100_warp_b1024.json", "yu2019_ditch_cpg_es_h100_warp_b1024.json"


def res(name, terrain, variant):
    return js(name)["results"][terrain][variant]


def cmp(name, terrain, pair):
    return js(name)["comparisons"][terrain][pair]


def per_env(name, terrain, variant, key):
    return np.asarray(res(name, terrain, variant)["per_env"][key], dtype=float)


def median_found_depth(name, terrain, variant="reflexes"):
    d = per_env(name, terrain, variant, "search_depth_mm")
    return float(np.median(d[d > 0]))


def yu_step(terrain):
    r = res(S, terrain, "reflexes")
    out = [f"{pct(r['success_rate'])} % cross", f"{pct(r['fall_rate'])} % fall"]
    if terrain == "step40":
        out.append(f"{f1(r['elevator_triggers_mean'])} elevator reflexes a run")
    return out


def yu_no_elevator():
    out = []
    for t in ("step40", "step50"):
        ne = res(S, t, "no-elevator")["success_rate"]
        out += [f"{pct(ne)} %", f"gain {diff(cmp(S, t, 'reflexes - no-elevator')['success_pts'])}"]
    return out


def yu_blind():
    b40, b50 = res(S, "step40", "blind"), res(S, "step50", "blind")
    assert b40["success_rate"] == b50["success_rate"] == 0
    return ["0 % cross (both heights)", f"right feet on top in {pct(b40['right_feet_up_rate'])} % (40 mm) and "
            f"{pct(b50['right_feet_up_rate'])} % (50 mm) of runs", f"{b40['heading_change_deg_mean_abs']:.0f} deg (40 mm)",
            f"{b50['heading_change_deg_mean_abs']:.0f} deg (50 mm)"]


def yu_footholds():
    a, b = res(D, "ditch18", "reflexes"), res(D, "ditch40", "reflexes")
    return [f"{pct(a['envs_with_found_foothold'])} % (18 mm) and {pct(b['envs_with_found_foothold'])} % (40 mm)",
            f"median kinematic depth of {median_found_depth(D, 'ditch18'):.0f} and "
            f"{median_found_depth(D, 'ditch40'):.0f} mm",
            f"{pct(a['success_rate'])} % and {pct(b['success_rate'])} % cross",
            f"in {pct(a['floor_reached_rate_of_feet_over_ditch'], 0)} % and "
            f"{pct(b['floor_reached_rate_of_feet_over_ditch'])} % of runs",
            f"({pct(res(D, 'ditch40', 'no-search')['floor_reached_rate_of_feet_over_ditch'], 0)} %)"]


def yu_search_vs_blind():
    c = {t: cmp(D, t, "reflexes - no-search") for t in ("ditch18", "ditch40", "ditch80")}
    d40, l40, h40 = c["ditch40"]["success_pts"]
    f40, fl, fh = c["ditch40"]["fall_pts"]
    return [f"18 mm: {diff(c['ditch18']['success_pts'])} success",
            f"40 mm: {sg(d40)} {ci(l40, h40)} success but {sg(f40)} {ci(fl, fh)} falls",
            f"80 mm: {sg(c['ditch80']['success_pts'][0])} {ci(*c['ditch80']['success_pts'][1:])} success"]


def yu_give_up():
    r = res(D, "ditch80", "reflexes")
    assert r["failed_with_alien_group_in_stance_prolong"] == 1.0
    return [f"{pct(per_env(D, 'ditch80', 'reflexes', 'gave_up').mean())} % of runs give up",
            f"within {f1(r['failed_leg_aep_error_mm_max'])} mm of its AEP posture",
            f"{pct(r['success_rate'])} % of runs cross", f"({pct(res(D, 'ditch80', 'no-search')['success_rate'])} % without"]


def yu_walk_on():
    gave, crossed = per_env(D, "ditch80", "walk-on", "gave_up") > 0, per_env(D, "ditch80", "walk-on", "crossed") > 0
    assert not (gave & crossed).any()
    return [f"{pct(res(D, 'ditch80', 'walk-on')['success_rate'])} % cross",
            f"{diff(neg(cmp(D, 'ditch80', 'reflexes - walk-on')['success_pts']))} from walking on",
            f"none of the {int(gave.sum())} runs"]


def yu_tuned_search():
    c = {t: cmp(E, t, "reflexes - no-search") for t in ("ditch18", "ditch40", "ditch80")}
    return [f"18 mm: {diff(c['ditch18']['success_pts'])}",
            f"40 mm: {sg(c['ditch40']['success_pts'][0])} {ci(*c['ditch40']['success_pts'][1:])} success and "
            f"{sg(c['ditch40']['fall_pts'][0])} {ci(*c['ditch40']['fall_pts'][1:])} falls",
            f"80 mm: {sg(c['ditch80']['success_pts'][0])} {ci(*c['ditch80']['success_pts'][1:])}"]


def yu_tuned_80():
    r, w, n = (res(E, "ditch80", v) for v in ("reflexes", "walk-on", "no-search"))
    return [f"{pct(r['success_rate'])} % cross with the search", f"{pct(w['success_rate'])} % walking on",
            f"{pct(n['success_rate'])} % without the search", f"{pct(r['fall_rate'])} % fall",
            f"{pct(per_env(E, 'ditch80', 'reflexes', 'gave_up').mean())} % of runs give up"]


def yu_tuned_18_40():
    a, b = res(E, "ditch18", "reflexes"), res(E, "ditch40", "reflexes")
    na, nb = res(E, "ditch18", "no-search"), res(E, "ditch40", "no-search")
    return [f"{pct(a['success_rate'])} % and {pct(b['success_rate'])} % cross",
            f"(no-search {pct(na['success_rate'])} % and {pct(nb['success_rate'])} %)",
            f"footholds found in {pct(b['envs_with_found_foothold'])} % of 40 mm runs",
            f"median kinematic depth of {median_found_depth(E, 'ditch40'):.0f} mm"]


N = "yu2019_network_cpu.json"


def yu_lock():
    p = js(N)["phase_lock"]
    return [f"median {p['k=0.1']['median_s']:.0f} s, 90 % by {p['k=0.1']['p90_s']:.0f} s",
            f"median {p['k=1']['median_s']:.1f} s, 90 % by {p['k=1']['p90_s']:.1f} s"]


def yu_gaits():
    g = js(N)["gaits"]["gaits"]
    order = ("tripod", "tetrapod", "wave")
    assert all(g[k]["fell"] == 0 and g[k]["legs_in_swing_max"] == g[k]["legs_in_swing_eq16"] for k in order)
    return ["Duty factors " + ", ".join(f"{g[k]['duty_factor']:.3f}" for k in order),
            "and " + ", ".join(f"{g[k]['legs_in_swing_mean']:.0f}" for k in order) + " legs in swing",
            ", ".join(f"{1000 * g[k]['speed_m_s']:.0f}" for k in order[:2]) + f" and "
            f"{1000 * g['wave']['speed_m_s']:.0f} mm/s"]


# ---- Zhao 2018, Chen 2019 ------------------------------------------------------------------------------------

def zh_exp1():
    z = js("zhao2018.json")
    assert z["reached"] and z["cycles"] == z["cycles_table2"]
    return [f"{z['cycles']} cycles", f"{100 * z['mean_distance_to_table2']:.1f} cm from",
            f"{100 * z['max_distance_to_table2']:.1f} cm at most", f"clearance {100 * z['min_clearance']:.1f} cm"]


def zh_random():
    z = js("zhao2018_random_cpu_10000.json")
    return [f"{pct(z['success_rate'], 0)} % of {z['fields']:,} random fields", f"{z['collisions']} collisions",
            f"clearance {100 * z['min_clearance']['min']:.1f} cm", f"path {z['path_ratio']['mean']:.3f}x"]


def zh_mjx():
    z = js("zhao2018_mjx_h100_warp_b4096.json")
    m = z["mjx"]
    return [f"among {100 * z['config']['obstacle_height']:.0f} cm boxes", f"{pct(m['success_rate_all'])} % reach",
            f"{m['touched']} touches", f"{m['fell']} falls", f"{100 * m['final_distance_m']['median']:.1f} cm median"]


def zh_perception():
    m = js("zhao2018_perception_cpu_b16.json")["modes"]
    return [f"{pct(m['perceived']['success_rate'], 0)} % success", f"{m['perceived']['touched']} collisions",
            f"({pct(m['privileged']['success_rate'], 0)} %)", f"blind {pct(m['blind']['success_rate'])} %",
            f"{pct(m['blind']['collision_rate'])} % collisions"]


def ch_planned():
    p = js("chen2019_h100_warp_b1024.json")["planned"]
    n = js("chen2019_h100_warp_b1024.json")["config"]["patches"]
    return [f"{p['crossed']} of {n} cross", f"{p['capsized']} capsize",
            f"{f1(p['max_tilt_deg']['median'])} deg median", f"{f1(p['max_tilt_deg']['max'])} deg worst",
            f"{100 * p['min_stability_margin_m']['min']:.1f} cm"]


def ch_fixed():
    j = js("chen2019_h100_warp_b1024.json")
    a, b = j["fixed_h8cm"], j["fixed_h13cm"]
    n = j["config"]["patches"]
    return [f"{a['crossed']} of {n} cross ({a['stalled']} stall), {a['capsized']} capsize",
            f"{b['crossed']} of {n} cross, {b['tilted_over_30deg']} tilt past", f"{b['capsized']} capsize"]


def ch_incenter():
    s = js("chen2019_incenter_cpu_100k.json")["by_sides"]
    assert all(v["radius_shortfall"]["p50"] < 1e-6 and v["iterative_exceeds_exact"] == 0 for v in s.values())
    w = [v["within_1e-3"] for v in s.values()]
    hi = "100" if max(w) == 1.0 else pct(max(w))
    return [f"{pct(min(w))}-{hi} %"]


def ch_perception():
    j = js("chen2019_perception_cpu_b8.json")
    p, t, m = j["perceived"], j["planned"], j["perceived"]["map"]
    n = p["crossed"] + p["stalled"]
    return [f"{p['crossed']} of {n} cross", f"{p['capsized']} capsize", f"({t['crossed']} of {n} on the true DEM)",
            f"worst tilt {p['max_tilt_deg']['max']:.0f} deg against {t['max_tilt_deg']['max']:.0f} deg",
            f"sees {pct(m['seen_share'], 0)} %", f"within {1000 * m['seen_cells']['mean_abs']:.1f} mm mean",
            f"{1000 * m['seen_cells']['p95_abs']:.1f} mm p95"]


# ---- tuned presets ---------------------------------------------------------------------------------------------

def tuned(name, falls):
    j = js(name)
    a, b = j["start"]["held_out"], j["final"]["held_out"]
    out = [f"{a['objective']:.3f} -> **{b['objective']:.3f}** ({100 * (b['objective'] / a['objective'] - 1):+.0f} %)",
           f"{f1(a['goal_error_cm'])} -> {f1(b['goal_error_cm'])} cm"]
    if falls:
        out.append(f"falls {f1(a['fall_pct'])} -> {f1(b['fall_pct'])} %")
    else:
        assert a["fall_pct"] == b["fall_pct"] == 0
        out.append("no falls")
    return out


# (key that finds the row, columns holding measured figures, rule, numbers given as inputs)
ROWS = [
    ("On flat ground the robot ends 1-5 cm", [1], lu_flat, ["1 / 2 m"]),
    ("Without the method legs get stuck", [1], lu_stuck, []),
    ("Relative error up to ~24 %", [1], lu_rel, ["at 1 m"]),
    ("The method lowers the error (Figs", [1], lu_lower, []),
    ("With the method the error is 4.16-16.5 cm", [1], lu_fig20, []),
    ("The wave gait deviates less than", [1], lu_wave, []),
    ("The analytic model (Eqs. 8-14)", [1], lu_model, ["the 1 m readout", "wave 1 m", "tripod 1 m"]),
    ("| without the method | ", [1, 2, 3, 4], lambda: lu_breakdown("without"), []),
    ("| with the method | ", [1, 2, 3, 4], lambda: lu_breakdown("with"), []),
    ("A recurrent network (ReLU embedding", [1], lu_predictor, ["every 5 cm", "(Eq. 8,"]),
    ("The elevator reflex carries the robot over a 40 mm step", [1], lambda: yu_step("step40"), []),
    ("... and a 50 mm step", [1], lambda: yu_step("step50"), []),
    ("Without the elevator reflex the leg stumbles", [1], yu_no_elevator, ["40 mm:", "50 mm:"]),
    ("The blind CPG cannot take the step", [1], yu_blind, []),
    ("The searching reflex finds footholds in 18 and 40 mm", [1], yu_footholds, ["within 3 mm"]),
    ("Searching does not make a ditch worse", [1], yu_search_vs_blind, []),
    ("On an 80 mm ditch the leg finds nothing", [1], yu_give_up, []),
    ("... while the robot still crosses", [1], yu_walk_on, []),
    ("the searching reflex never makes a ditch worse", [1], yu_tuned_search, []),
    ("... and the robot crosses the 80 mm ditch", [1], yu_tuned_80, []),
    ("... and on 18 and 40 mm", [1], yu_tuned_18_40, []),
    ("The followers lock onto the leader", [1], yu_lock, ["Table 1's k = 0.1", "k = 1"]),
    ("Eq. 16 turns the tripod into", [1], yu_gaits,
     ["Eq. 16's (gamma - 1) / gamma and 6 / gamma for gamma = 2, 3, 6"]),
    ("Experiment 1 reaches the target", [1], zh_exp1, ["Table 2's"]),
    ("The planner avoids obstacles in general", [1], zh_random, []),
    ("The planned motion carries a walking robot", [1], zh_mjx, []),
    ("The planner runs on a 2.5D grid map", [1], zh_perception, []),
    ("Support planning crosses the rugged patch", [1], ch_planned, []),
    ("Fixed motions capsize the robot", [1], ch_fixed, ["8 cm swing", "13 cm:", "30 deg"]),
    ("The iterative incenter (Sect. 2.2", [1], ch_incenter, ["below 1e-6", "within 1e-3", "(3-6 sides)"]),
    ("the DEM is the one the robot's depth camera maps", [1], ch_perception, ["2.5D"]),
    ("| `tactile_tripod_es` |", [3, 4], lambda: tuned("tune_tactile_es_validated_cpu.json", False), []),
    ("| `tactile_tripod_grad` |", [3, 4], lambda: tuned("tune_tactile_grad_validated_cpu.json", False), []),
    ("| `cpg_step_ditch_es` |", [3, 4], lambda: tuned("tune_cpg_es_validated_gpu.json", True), []),
    ("| `cpg_step_ditch_grad` |", [3, 4], lambda: tuned("tune_h100_validated_cpg_sgd_cold_log.json", True), []),
    ("| `cpg_reflex_es` |", [3, 4], lambda: tuned("tune_cpg_reflex_es_h100.json", True), []),
]


@pytest.mark.parametrize("key,cols,rule,given", ROWS, ids=[r[0][:40] for r in ROWS])
def test_a_results_row_states_the_figures_of_its_json(key, cols, rule, given):
    cells = row_of(key)
    text = " | ".join(cells[c] for c in cols)
    for want in rule():
        assert want in text, f"docs/results.md row {key!r}: {want!r} (from its JSON) is not in {text!r}"
        text = text.replace(want, " ", 1)
    for g in given:
        text = text.replace(g, " ")
    left = re.findall(r"[-+]?\d[\d,.]*", text)
    assert not left, f"docs/results.md row {key!r}: numbers no rule reads from the JSON: {left} in {text!r}"


def test_every_row_naming_a_json_is_checked():
    """A table whose rows or whose text above names a JSON of docs/results/ has every row under a rule here."""
    keys = [r[0] for r in ROWS]
    unchecked = [row[:80] for above, rows in _tables(open(PAGE, encoding="utf-8").read().splitlines())
                 if ".json" in above + " ".join(rows) for row in rows[2:] if not any(k in row for k in keys)]
    assert not unchecked, f"docs/results.md rows of a table with JSONs but no rule in this test: {unchecked}"


def _tables(page):
    """[(the text between the previous table and this one, this table's lines)], header and rule included."""
    out, above = [], []
    for ln in page:
        if _is_row(ln):
            if not out or out[-1][1] is None or above:
                out.append((" ".join(above), []))
                above = []
            out[-1][1].append(ln)
        else:
            above.append(ln)
    return out


def test_the_checker_fails_on_a_figure_its_json_does_not_hold(monkeypatch, tmp_path):
    """The same check on a copy of the page whose 2 m range is off by a centimetre."""
    page = open(PAGE, encoding="utf-8").read()
    lo, hi = lu_fig20()[1].split(" cm")[0].split("-")
    bad = page.replace(f"{lo}-{hi} cm at 2 m", f"{lo}-{float(hi) + 1:.1f} cm at 2 m")
    assert bad != page
    p = tmp_path / "results.md"
    p.write_text(bad, encoding="utf-8")
    monkeypatch.setattr(sys.modules[__name__], "PAGE", str(p))
    with pytest.raises(AssertionError, match="not in"):
        test_a_results_row_states_the_figures_of_its_json(*ROWS[4])
