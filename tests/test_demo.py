"""The quickstart's edit picture: its layout, tile by tile (the edits themselves are tested
end to end in tests/test_cli_train_render.py::test_quickstart_end_to_end)."""

from __future__ import annotations

import numpy as np

from crfedit.demo import tiled


def test_tiled_places_each_image_scaled_under_its_label_with_gaps_between_groups():
    colours = [[(1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 1, 0), (0, 1, 1)], [(0.5, 0.5, 0.5)]]
    rows = [[np.broadcast_to(np.array(c, dtype=np.float64), (2, 3, 3)) for c in row] for row in colours]
    out = tiled(rows, [["a"] * 5, ["b"]], scale=2, group=3)
    pad, gap, text_h, h, w = 6, 18, 16, 4, 6  # a 2×3 image at scale 2 is 4 × 6
    assert out.shape == (2 * (h + text_h + pad) + pad, pad + 4 * (w + pad) + 2 * gap + w + pad, 3)
    # column c starts at pad + c·(w + pad), plus one gap before column 1 and another before column 4
    for r, row in enumerate(colours):
        y = pad + r * (h + text_h + pad) + text_h
        for c, colour in enumerate(row):
            x = pad + c * (w + pad) + gap * ((c - 1) // 3 + 1 if c else 0)
            tile = out[y:y + h, x:x + w]
            assert (tile == np.round(np.array(colour) * 255)).all(), (r, c)
            assert (out[y:y + h, x + w] == 255).all()  # white after each tile
    assert (out[pad + h + text_h + pad + text_h:, pad + w + pad:] == 255).all()  # the second row's one image only
