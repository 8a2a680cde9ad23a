"""H.264 MP4 writing: codec, frame count, odd sizes padded, content close to the frames."""

from __future__ import annotations

import av
import numpy as np
import pytest

from damcap.common.errors import DamcapError
from damcap.export.video import H264Writer


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
