"""One scoring path (issue 36): a method has the same mAP in every table that shows it.

Every method of the study is mapped to each test frame's branch set and scored once by
`study.pipeline.evaluation.Methods.score` (`results["methods"]`); HydraFusion's Tables 2, 3, 5 and 6 and
EcoFusion's Tables 1 and 2 show some of those methods again. `shown_maps` lists, per method, every
place a results record shows its mAP (the table, the row and the fusion it was fused with), and
`disagreements` the places whose value is not the method's own, within the tables' rounding. The
evaluation records them (`results["one_path"]`), the report prints any, and the tests hold the
tables to it.

A table cell counts only where it claims the study's method: the same branch sets, fused with the
study's fusion method at the study's k (Table 6's other fusion columns and Table 3's other k are
other methods, not checked against these).
"""

from __future__ import annotations

TOLERANCE = 1.5e-4
"""The tables round mAP to 4 decimals: two roundings of one number differ by at most 1e-4."""


def _label(fusion: str) -> str:
    return str(fusion).replace("_", "-")


def shown_maps(r: dict) -> dict[str, list[tuple[str, float]]]:
    """{method: [(where, mAP), ...]} of every table of results `r` that shows a method of
    `r["methods"]` with the study's fusion method (`r["fusion"]`) at its k."""
    methods, fusion, k = r["methods"], _label(r["fusion"]), str(r["k"])
    out: dict[str, list[tuple[str, float]]] = {}

    def add(method: str, where: str, value) -> None:
        if method in methods and value is not None:
            out.setdefault(method, []).append((where, float(value)))

    t2 = r.get("hydra_table2") or {}
    for b, v in (t2.get("single_sensors") or {}).items():
        add(f"single:{b}", f"HydraFusion Table 2, single sensor {b}", v)
    for b, v in (t2.get("early_fusion") or {}).items():
        add(f"early:{b}", f"HydraFusion Table 2, early fusion {b}", v)
    add("all_branches", "HydraFusion Table 2, all branches",
        (t2.get("late_fusion") or {}).get("all_branches (early + late)"))
    for row, v in (t2.get("hydrafusion") or {}).items():
        add(f"hydrafusion:{row.split(' top ')[0]}", f"HydraFusion Table 2, {row}", v)
    for row, v in (t2.get("ecofusion") or {}).items():
        add(f"ecofusion:{row.split(' lambda_E ')[0]}", f"HydraFusion Table 2, EcoFusion {row}", v)
    for g, row in (r.get("hydra_table3") or {}).items():
        if _label(row.get("fusion", "")) == fusion:
            add(f"hydrafusion:{g}", f"HydraFusion Table 3, {g} top {k}", (row.get("map") or {}).get(k))
    for g, cols in (r.get("hydra_table6") or {}).items():
        for f, by_k in cols.items():
            if _label(f) == fusion:
                add(f"hydrafusion:{g}", f"HydraFusion Table 6, {g} top {k} by {f}", (by_k or {}).get(k))
    late = "+".join(r.get("late") or [])
    for combo, row in (r.get("hydra_table5") or {}).items():
        if combo == late:
            for f, v in row.items():
                if _label(f) == fusion:
                    add("late", f"HydraFusion Table 5, {combo} by {f}", v)
    eco = r.get("eco") or {}
    if eco.get("data_fusion") is None or _label(eco.get("data_fusion")) == fusion:
        for name, row in (eco.get("table1") or {}).items():
            if name.startswith("none_"):
                add(f"single:{name[5:]}", f"EcoFusion Table 1, {name}", row.get("map"))
            elif name == "late":
                add("late", "EcoFusion Table 1, late", row.get("map"))
            elif name == f"ecofusion_{r.get('eco_gate')}_lambda_{r.get('lambda_e'):g}":
                add(f"ecofusion:{r.get('eco_gate')}", f"EcoFusion Table 1, {name}", row.get("map"))
        for g, row in ((eco.get("table2") or {}).get(f"{r.get('lambda_e'):g}") or {}).items():
            add(f"ecofusion:{g}", f"EcoFusion Table 2, {g} at lambda_E {r.get('lambda_e'):g}", row.get("map"))
    return out


def disagreements(r: dict) -> list[dict]:
    """The places of `shown_maps` whose mAP differs from the method's own by more than TOLERANCE."""
    out = []
    for method, places in shown_maps(r).items():
        own = float(r["methods"][method]["map"])
        for where, value in places:
            if abs(value - own) > TOLERANCE:
                out.append({"method": method, "where": where, "shown": round(value, 4), "own": round(own, 4)})
    return out


def one_path_record(r: dict) -> dict:
    """results["one_path"]: how many table cells were checked against their method's own mAP, and
    the ones that disagree (none when every table reads the one scoring path)."""
    places = shown_maps(r)
    return {"checked": sum(len(v) for v in places.values()), "methods": sorted(places),
            "disagreements": disagreements(r)}
