"""Photos from a video: the sharpest frame of each stretch, written as JPEGs with a record."""

from __future__ import annotations

import json

import numpy as np
import pytest

from damcap.capture.video import VideoFrameOptions, extract_video_frames, pick_video_frames
from damcap.common.errors import DamcapError
from damcap.common.exr import read_image_u8


@pytest.fixture(scope="module")
def video(tmp_path_factory):
    """40 frames of a texture sliding sideways; every 4th frame (1, 5, 9, ...) sharp, the others blurred."""
    import cv2

    from damcap.export.video import H264Writer

    rng = np.random.default_rng(0)
    tex = cv2.resize((rng.random((50, 100, 3)) * 255).astype(np.uint8), (400, 200), interpolation=cv2.INTER_NEAREST)
    path = tmp_path_factory.mktemp("video") / "turn.mp4"
    writer = H264Writer(path, 24)
    for k in range(40):
        frame = np.roll(tex, 5 * k, axis=1)[:, :320]
        writer.write(frame if k % 4 == 1 else cv2.GaussianBlur(frame, (0, 0), 3))
    writer.close()
    return path


def test_the_sharp_frames_of_each_stretch_are_kept(video, tmp_path):
    record = extract_video_frames(video, tmp_path / "photos", VideoFrameOptions(count=10))
    assert record["video_frames_decoded"] == 40 and [p["video_frame_index"] for p in record["photos"]] == list(range(1, 40, 4))
    names = sorted(p.name for p in (tmp_path / "photos").glob("*.jpg"))
    assert names == [f"frame_{k:05d}.jpg" for k in range(1, 40, 4)]
    assert read_image_u8(tmp_path / "photos" / names[0]).shape == (200, 320, 3)
    assert json.loads((tmp_path / "photos" / "frames.json").read_text())["count"] == 10
    times = [p["time_s"] for p in record["photos"]]
    assert times == sorted(times) and times[1] - times[0] == pytest.approx(4 / 24, abs=1e-3)


def test_photos_are_downscaled_to_max_side(video, tmp_path):
    calls: list[tuple[str, int, int]] = []
    extract_video_frames(video, tmp_path / "small", VideoFrameOptions(count=3, max_side=160), progress=lambda *a: calls.append(a))
    assert calls[-1] == ("writing", 3, 3) and ("scoring", 40, 40) in calls  # the container says 40 frames
    assert read_image_u8(next((tmp_path / "small").glob("*.jpg"))).shape == (100, 160, 3)


def test_pick_video_frames_spreads_over_the_video():
    assert pick_video_frames(np.ones(100), 4) == [0, 25, 50, 75]
    assert pick_video_frames(np.arange(10.0), 2) == [4, 9]


def test_what_is_not_a_video_is_refused_in_one_line(tmp_path):
    bad = tmp_path / "notes.mp4"
    bad.write_text("not a video")
    with pytest.raises(DamcapError, match="notes.mp4: cannot read a video here"):
        extract_video_frames(bad, tmp_path / "out", VideoFrameOptions())
    with pytest.raises(DamcapError, match="video file not found"):
        extract_video_frames(tmp_path / "missing.mp4", tmp_path / "out", VideoFrameOptions())


def test_a_phone_video_is_turned_upright_as_its_display_matrix_says(tmp_path):
    """Phones store portrait video as landscape frames plus a rotation: the photos are upright."""
    import av

    path = tmp_path / "portrait.mp4"
    with av.open(str(path), "w") as c:
        s = c.add_stream("libx264", rate=10)
        s.width, s.height, s.pix_fmt = 64, 32, "yuv420p"
        s.set_display_rotation(-90)  # as a phone held upright records: turn clockwise to show
        img = np.zeros((32, 64, 3), np.uint8)
        img[:, :16] = 255  # the sensor's left edge
        for _ in range(3):
            for packet in s.encode(av.VideoFrame.from_ndarray(img, format="rgb24")):
                c.mux(packet)
        for packet in s.encode():
            c.mux(packet)
    record = extract_video_frames(path, tmp_path / "photos", VideoFrameOptions(count=2))
    assert record["display_rotation_deg"] == [-90.0]
    photo = read_image_u8(tmp_path / "photos" / record["photos"][0]["photo"])
    assert photo.shape == (64, 32, 3)  # portrait
    assert photo[:12].mean() > 200 and photo[20:].mean() < 50  # the sensor's left edge is on top


def test_a_video_whose_frames_exceed_memory_is_refused_before_decoding(video, tmp_path, monkeypatch):
    from damcap.common import validate

    monkeypatch.setattr(validate, "machine_memory_bytes", lambda: 2 * 2 ** 20)  # 1 MiB allowed: a 320x200 frame needs 1.34 MiB
    with pytest.raises(DamcapError, match=r"turn.mp4: an image of 320x200 pixels, 3 channels would need 0.00131 GiB of memory"):
        extract_video_frames(video, tmp_path / "photos", VideoFrameOptions(count=3))
    assert not (tmp_path / "photos").exists()
