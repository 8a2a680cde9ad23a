"""bench.synth's table1 stage at tiny sizes: two 16 px Mitsuba captures (point light, environment map)."""

from __future__ import annotations

import json

from bench import synth


def test_synth_table1_stage_writes_table(tmp_path, shared_data, corpus_writer, is_dssim):
    from damcap.synth.mitsuba_capture import SynthOptions, make_synthetic_capture

    corpus = tmp_path / "corpus"
    lights = [("sphere__point__m1", "point", "point:52.5:22.9"),
              ("sphere__env-sunset__m1", "env", f"env:{shared_data / 'envmaps' / 'sunset.hdr'}:90")]
    for name, _, light in lights:
        make_synthetic_capture(corpus / "captures" / name, SynthOptions(object="sphere", light=light, views=4, train_views=2,
                                                                        resolution=16, spp=4, seed=1, supersample=2))
    corpus_writer(corpus, [(name, kind, 1, light) for name, kind, light in lights])
    out = tmp_path / "out"
    argv = ["--stages", "table1", "--corpus", str(corpus), "--fit-seeds", "0", "--fit-steps", "20", "--floor-every", "1",
            "--out", str(out)]
    assert synth.main(argv) == 0
    doc = json.loads((out / "synth.json").read_text())
    assert doc["command"] == ".venv/bin/python -m bench.synth"
    assert doc["runs"][-1]["command"] == ".venv/bin/python -m bench.synth " + " ".join(argv)
    t1 = doc["table1"]
    assert t1["fit_options"]["steps"] == 20 and t1["captures"] == [name for name, _, _ in lights]
    for kind in ("point", "env"):
        for view in ("same_view", "novel_view"):
            cell = t1["table"][kind][view]
            assert is_dssim(cell["DAM"]) and is_dssim(cell["RM++"]) and is_dssim(cell["RM"]) and is_dssim(cell["noise_floor"])
            assert abs(cell["DAM/RM++"] - cell["DAM"] / cell["RM++"]) < 1e-12
    md = (out / "synth.md").read_text()
    assert "Command (from the repository root): `.venv/bin/python -m bench.synth`" in md
