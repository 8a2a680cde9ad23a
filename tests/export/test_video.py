"""H.264 MP4 writing: codec, frame count, odd sizes padded, content close to the frames, faststart,
and the turntable's timing (at least 3 s whatever the number of views)."""

from __future__ import annotations

import av
import numpy as np
import pytest

from damcap.common.errors import DamcapError
from damcap.export.video import H264Writer, mp4_top_level_boxes, turntable_timing


def _write_turntable(path, views, fps_max=24):
    """An orbit of ``views`` distinct frames written as export does: turntable_timing's rate, repeated turns."""
    timing = turntable_timing(views, fps_max)
    orbit = [np.full((16, 16, 3), 10 * k, np.uint8) for k in range(views)]
    with H264Writer(path, fps=timing.fps) as w:
        for _ in range(timing.turns):
            for frame in orbit:
                w.write(frame)
    return timing


def test_frames_round_trip_as_h264(tmp_path):
    path = tmp_path / "t.mp4"
    ramp = np.broadcast_to(np.linspace(0, 255, 33)[None, :, None], (31, 33, 3)).astype(np.uint8)
    with H264Writer(path, fps=12) as w:
        for k in range(5):
            w.write(np.roll(ramp, 3 * k, axis=1))
    with av.open(str(path)) as video:
        s = video.streams.video[0]
        assert s.codec_context.name == "h264" and (s.codec_context.width, s.codec_context.height) == (34, 32)
        frames = [f.to_ndarray(format="rgb24") for f in video.decode(s)]
    assert len(frames) == 5
    assert np.abs(frames[1][:31, :33].astype(int) - np.roll(ramp, 3, axis=1).astype(int)).mean() < 4


def test_an_unwritable_place_is_one_clear_error(tmp_path):
    with pytest.raises(DamcapError, match="cannot write an MP4 here"):
        w = H264Writer(tmp_path / "missing" / "t.mp4", fps=24)
        w.write(np.zeros((8, 8, 3), np.uint8))
        w.close()


def test_24_views_play_3_seconds_with_the_index_first(tmp_path):
    path = tmp_path / "t.mp4"
    timing = _write_turntable(path, 24)
    boxes = mp4_top_level_boxes(path.read_bytes())
    assert boxes[0] == "ftyp" and boxes.index("moov") < boxes.index("mdat")  # faststart
    with av.open(str(path)) as video:
        s = video.streams.video[0]
        assert abs(video.duration / av.time_base - 3.0) < 0.01
        assert s.frames == 24 and s.average_rate == 8
        assert abs(float(s.duration * s.time_base) - 3.0) < 0.01
    assert (timing.fps, timing.turns, timing.duration_s) == (8, 1, 3.0)


def test_few_views_repeat_the_orbit_to_3_seconds(tmp_path):
    path = tmp_path / "t.mp4"
    timing = _write_turntable(path, 5)
    assert (timing.fps, timing.turns) == (8, 5) and timing.duration_s == pytest.approx(25 / 8)
    with av.open(str(path)) as video:
        assert abs(video.duration / av.time_base - 25 / 8) < 0.01
        grey = [int(f.to_ndarray(format="rgb24")[8, 8, 0]) for f in video.decode(video.streams.video[0])]
    assert len(grey) == 25 and all(abs(g - 10 * (k % 5)) <= 3 for k, g in enumerate(grey))  # the orbit, whole, five times


@pytest.mark.parametrize("views, fps_max, expected", [
    (24, 24, (8, 1, 3.0)), (36, 24, (12, 1, 3.0)), (72, 24, (24, 1, 3.0)), (100, 24, (24, 1, 100 / 24)),
    (25, 24, (8, 1, 25 / 8)), (12, 24, (8, 2, 3.0)), (1, 24, (8, 24, 3.0)), (24, 5, (5, 1, 24 / 5)), (4, 2, (2, 2, 4.0)),
])
def test_turntable_timing(views, fps_max, expected):
    t = turntable_timing(views, fps_max)
    assert (t.fps, t.turns) == expected[:2] and t.duration_s == pytest.approx(expected[2])
    assert t.duration_s >= 3.0 and (t.turns == 1 or (t.turns - 1) * views / t.fps < 3.0)  # no more turns than needed


def test_turntable_timing_rejects_no_views():
    with pytest.raises(DamcapError, match="views, fps_max, fps_floor >= 1"):
        turntable_timing(0, 24)


def test_mp4_boxes_of_a_truncated_file_is_one_clear_error():
    with pytest.raises(DamcapError, match="declares size 3"):
        mp4_top_level_boxes(b"\x00\x00\x00\x03ftyp")
