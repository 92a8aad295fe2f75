"""benchmarks/landing_spots_ab.py: another revision's landing-spot choice beside this one's."""

import numpy as np

from cfrace.track import load_track


def test_a_revision_against_itself_gives_the_same_spots(bench_script):
    ab = bench_script("landing_spots_ab")
    import cfrace.flight.landing.spots as new

    old = ab.load_revision("HEAD")
    assert old is not new and old.choose_landing_spots is not new.choose_landing_spots
    r = ab.compare(old, new, "complex", 4, 2)
    assert r["same_spots"] and r["ms"]["tick old max"] > 0.0 and r["ms"]["tick new max"] > 0.0
    track = load_track("lemniscate")
    spots, took = ab.land_one_by_one(new, track, np.array([[0.0, 4.0], [0.1, 4.0]]))
    assert spots is not None and len(took) == 2
    assert np.linalg.norm(spots[0] - spots[1]) >= new.LandingConfig().drone_separation_m - 1e-9
