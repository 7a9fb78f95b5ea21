"""The pictures: the overview figure's layout, panels and titles."""

import numpy as np

from colorps.figures import PANEL_MARGIN, PANEL_SIDE, TITLE_PX, overview
from colorps.io import srgb_encode


def _scene(h=60, w=90):
    normals = np.zeros((h, w, 3), dtype=np.float32)
    normals[..., 2] = 1.0
    albedo = np.broadcast_to(np.float32([0.5, 0.1, 0.02]), (h, w, 3)).copy()
    return normals, albedo, np.zeros((h, w), dtype=np.float32)


def test_overview_places_each_panel_under_its_title():
    normals, albedo, height = _scene()
    figure = overview(albedo, normals, albedo, height, title="a title")
    cell = PANEL_SIDE + 2 * PANEL_MARGIN
    assert figure.shape == (2 * TITLE_PX + 2 * TITLE_PX + cell, 4 * cell, 3)
    assert figure.dtype == np.float32 and 0 <= figure.min() and figure.max() <= 1
    centre_y = 4 * TITLE_PX + PANEL_MARGIN + PANEL_SIDE // 2
    # The albedo panel (third) shows the albedo, sRGB-encoded; the normal panel
    # shows (n + 1) / 2 of a flat surface facing the camera.
    np.testing.assert_allclose(figure[centre_y, 2 * cell + cell // 2], srgb_encode(albedo[0, 0]),
                               atol=2e-3)
    np.testing.assert_allclose(figure[centre_y, cell + cell // 2], [0.5, 0.5, 1.0], atol=2e-3)
    # Titles are drawn: dark text on the white rows above the panels.
    titles = figure[2 * TITLE_PX:4 * TITLE_PX]
    for k in range(4):
        assert titles[:, k * cell:(k + 1) * cell].min() < 0.3
    assert figure[:2 * TITLE_PX].min() < 0.3  # the figure title
    # A wide image is fitted by its width and centred: white above and below it.
    assert figure[4 * TITLE_PX + PANEL_MARGIN + 5, 2 * cell + cell // 2].min() == 1.0


def test_overview_without_height_or_title_has_three_panels():
    normals, albedo, _ = _scene()
    grey = albedo[..., :1]
    figure = overview(grey, normals, grey, None)
    cell = PANEL_SIDE + 2 * PANEL_MARGIN
    assert figure.shape == (2 * TITLE_PX + cell, 3 * cell, 3)
    np.testing.assert_allclose(figure[2 * TITLE_PX + PANEL_MARGIN + PANEL_SIDE // 2,
                                      2 * cell + cell // 2],
                               srgb_encode(np.repeat(grey[0, 0], 3)), atol=2e-3)


def test_picture_codes_in_pieces_are_the_whole_picture_rounded(monkeypatch):
    """Made a few rows at a time, the codes are those of the whole picture
    rounded (uint8 and uint16), whatever the piece size."""
    import colorps.figures as figures

    rng = np.random.default_rng(3)
    picture = rng.uniform(-0.1, 1.1, (37, 23, 3)).astype(np.float32)
    monkeypatch.setattr(figures, "PICTURE_CHUNK", 50)  # two rows a piece
    for dtype, top in ((np.uint8, 255), (np.uint16, 65535)):
        codes = figures.picture_codes(lambda rows: picture[rows], picture.shape, dtype)
        assert codes.dtype == dtype
        np.testing.assert_array_equal(codes, np.rint(np.clip(picture, 0, 1) * np.float32(top)))
