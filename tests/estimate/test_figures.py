from torchsoil.estimate.figures import flag_runs


def test_flagged_windows_are_listed_as_runs_visit_by_visit():
    """Rows as a per-visit estimate yields them (window by window, visit 0 then 1): runs of
    windows one stride apart with the same flags become one line, each visit on its own."""
    rows = ([{"s": s, "visit": 0, "flags": "driven_again"} for s in (0.8, 1.2, 1.6)]
            + [{"s": 2.4, "visit": 0, "flags": "driven_again"}]                       # a gap: a run of its own
            + [{"s": s, "visit": v, "flags": "few_valid"} for s in (6.4, 6.8) for v in (0, 1)]
            + [{"s": 7.2, "visit": 0, "flags": "few_valid|stopped"}])
    assert flag_runs(rows, 0.4) == [
        "- s = 0.80-1.60 m (3 windows): driven_again",
        "- s = 2.40 m: driven_again",
        "- s = 6.40-6.80 m (2 windows): few_valid",
        "- s = 7.20 m: few_valid|stopped",
        "- s = 6.40-6.80 m (visit 1) (2 windows): few_valid",
    ]
