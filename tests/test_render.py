"""Offscreen rendering (film strips, animations, error heat maps), plots, and ``meshseq render``."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from conftest import shared_file
from PIL import Image

from meshseq import plots, render
from meshseq.cli import main
from meshseq.errors import MeshseqError, MeshseqWarning

WHITE = np.array(render.BACKGROUND)


@pytest.fixture(scope="module")
def horse():
    data = np.load(shared_file("horse-gallop.npz"))
    return data["vertices"].astype(np.float64), data["faces"].astype(np.int64)


def _foreground(image: np.ndarray, tol: int = 12) -> np.ndarray:
    """Boolean (H, W): pixels that differ from the white background."""
    return np.abs(image.astype(int) - WHITE).max(axis=-1) > tol


# --------------------------------------------------------------------------------------------
# Camera


def test_frame_camera_keeps_every_frame_in_view_and_fills_it(horse):
    verts, _ = horse
    cam = render.frame_camera(verts, height=150)
    pix, depth = cam.project(verts.reshape(-1, 3))
    assert np.all(depth > cam.znear) and np.all(depth < cam.zfar)
    assert pix[:, 0].min() >= 0 and pix[:, 0].max() <= cam.width
    assert pix[:, 1].min() >= 0 and pix[:, 1].max() <= cam.height
    # Tight: the motion's extent fills most of at least one image dimension.
    fill = max(np.ptp(pix[:, 0]) / cam.width, np.ptp(pix[:, 1]) / cam.height)
    assert fill > 0.8
    assert cam.height == 150 and cam.width % 2 == 0


def test_frame_camera_side_view_sees_the_long_axis(horse):
    # The horse gallops along z (its long horizontal axis); a side view shows that axis across
    # the image, so the image is wider than tall.
    verts, _ = horse
    cam = render.frame_camera(verts[0], azimuth=0.0, elevation=0.0)
    assert cam.width > 1.3 * cam.height
    assert abs(cam.pose[:3, 2] @ np.array([1.0, 0.0, 0.0])) > 0.99  # looks along x


def test_frame_camera_rejects_bad_input():
    with pytest.raises(MeshseqError, match="--up"):
        render.frame_camera(np.zeros((4, 3)) + np.arange(4)[:, None], up="w")
    with pytest.raises(MeshseqError, match="not finite"):
        render.frame_camera(np.full((4, 3), np.nan))


# --------------------------------------------------------------------------------------------
# Frame renderers


def test_egl_rendering_is_available_headless():
    ok, why = render.egl_available()
    assert ok, f"pyrender cannot render offscreen with EGL here ({why}); run tools/install_test_deps.sh"


@pytest.mark.parametrize("backend", ["pyrender", "matplotlib"])
def test_render_frames_shows_the_mesh_where_its_vertices_project(horse, backend):
    verts, faces = horse
    frames = verts[[0, 20, 40]]
    cam = render.frame_camera(frames, height=120)
    images = render.render_frames(frames, faces, cam, backend=backend)
    assert images.shape == (3, cam.height, cam.width, 3) and images.dtype == np.uint8
    for t in range(3):
        fg = _foreground(images[t])
        assert 0.05 < fg.mean() < 0.9, "image is blank or all mesh"
        # Every vertex lies on the surface: its pixel must be covered by the mesh.
        pix, _ = cam.project(frames[t])
        cols = np.clip(pix[:, 0].astype(int), 0, cam.width - 1)
        rows = np.clip(pix[:, 1].astype(int), 0, cam.height - 1)
        assert fg[rows, cols].mean() > 0.97
        # And the mesh covers nothing outside the vertices' projected bounding box (2 px slack).
        outside = np.ones_like(fg)
        outside[max(rows.min() - 2, 0) : rows.max() + 3, max(cols.min() - 2, 0) : cols.max() + 3] = False
        assert not fg[outside].any()
        # Shaded, not flat: the mesh pixels span a range of brightness.
        lum = images[t][fg].mean(axis=1)
        assert np.percentile(lum, 95) - np.percentile(lum, 5) > 30
    # The frames differ (the horse moves).
    assert (_foreground(images[0]) != _foreground(images[1])).mean() > 0.01


def test_both_renderers_agree_on_the_silhouette(horse):
    verts, faces = horse
    cam = render.frame_camera(verts[:1], height=100)
    a = _foreground(render.render_frames(verts[:1], faces, cam, backend="pyrender")[0])
    b = _foreground(render.render_frames(verts[:1], faces, cam, backend="matplotlib")[0])
    iou = (a & b).sum() / (a | b).sum()
    assert iou > 0.9


def test_missing_egl_falls_back_to_matplotlib_with_a_warning(horse, monkeypatch):
    verts, faces = horse
    monkeypatch.setattr(render, "_EGL_STATE", {"ok": False, "why": "no EGL in this test"})
    cam = render.frame_camera(verts[:1], height=60)
    with pytest.warns(MeshseqWarning, match="matplotlib"):
        img = render.render_frames(verts[:1], faces, cam)
    assert _foreground(img[0]).mean() > 0.05
    with pytest.raises(MeshseqError, match="EGL"):
        render.render_frames(verts[:1], faces, cam, backend="pyrender")


def test_vertex_colours_show_in_the_image(horse):
    verts, faces = horse
    cam = render.frame_camera(verts[:1], height=80)
    red = np.tile([1.0, 0.0, 0.0], (verts.shape[1], 1))
    img = render.render_frames(verts[:1], faces, cam, vertex_colors=red)[0]
    px = img[_foreground(img)].astype(int)
    assert np.median(px[:, 0] - px[:, 2]) > 40  # mostly red
    grey = render.render_frames(verts[:1], faces, cam)[0]
    gx = grey[_foreground(grey)].astype(int)
    assert abs(np.median(gx[:, 0] - gx[:, 2])) < 40


# --------------------------------------------------------------------------------------------
# Film strips, heat maps, animations


def test_film_strip_has_one_row_per_sequence_and_one_column_per_shown_frame(horse):
    verts, faces = horse
    short = verts[:20]  # frames 0 and 16 only
    cam = render.frame_camera([verts, short], height=60)
    img = render.film_strip([verts, short], faces, labels=["full", "short"], every=16, camera=cam)
    canvas, slots = render.layout_canvas(
        2, 3, cam.width, cam.height, row_labels=["full", "short"], col_labels=["frame 0", "frame 16", "frame 32"]
    )
    assert img.shape == canvas.shape
    for r in range(2):
        for c in range(3):
            y, x = slots[r, c]
            tile = img[y : y + cam.height, x : x + cam.width]
            has_mesh = _foreground(tile).mean() > 0.03
            assert has_mesh == (r == 0 or c < 2), (r, c)
    # Labels are drawn left of the tiles and above them.
    assert _foreground(img[:, : slots[0, 0, 1]]).any()
    assert _foreground(img[: slots[0, 0, 0]]).any()


def test_film_strip_default_every_limits_columns(horse):
    verts, faces = horse
    cam = render.frame_camera(verts, height=32)
    img = render.film_strip([verts[:, :]], faces, camera=cam, max_columns=4)  # 48 frames -> every 12
    canvas, _ = render.layout_canvas(1, 4, cam.width, cam.height, row_labels=["sequence 1"], col_labels=["frame 0"] * 4)
    assert img.shape == canvas.shape


def test_error_heat_map_colours_the_wrong_part_and_draws_a_colour_bar(horse):
    verts, faces = horse
    gt = verts[:2]
    pred = gt.copy()
    lifted = gt[0, :, 1] > np.percentile(gt[0, :, 1], 70)  # the top 30%: head and back
    pred[:, lifted, 1] += 0.05  # error 0.05 there, 0 elsewhere
    cam = render.frame_camera([gt, pred], height=100, elevation=0.0)
    img = render.film_strip([pred], faces, labels=["pred"], ground_truth=gt, every=1, camera=cam)
    _, slots = render.layout_canvas(2, 2, cam.width, cam.height, row_labels=["x"], col_labels=["y"])
    y, x = slots[1, 0]
    tile = img[y : y + cam.height, x : x + cam.width].astype(int)
    fg = _foreground(tile)
    hot = render.error_colors(np.array([0.05]), 0.05)[0] * 255
    cold = render.error_colors(np.array([0.0]), 0.05)[0] * 255
    # Pixels above the lifted threshold are hot (yellow: R, G high), those below are cold (dark).
    rows = np.nonzero(fg.any(axis=1))[0]
    top_band = fg.copy()
    top_band[rows.min() + int(0.25 * np.ptp(rows)) :] = False
    low_band = fg.copy()
    low_band[: rows.min() + int(0.75 * np.ptp(rows))] = False
    assert tile[top_band].mean(axis=0)[1] > tile[low_band].mean(axis=0)[1] + 60
    assert np.linalg.norm(hot - cold) > 200
    # The ground-truth row is uncoloured clay.
    gy, gx = slots[0, 0]
    gt_tile = img[gy : gy + cam.height, gx : gx + cam.width].astype(int)
    g = gt_tile[_foreground(gt_tile)]
    assert abs(np.median(g[:, 0] - g[:, 1])) < 25
    # The colour bar, right of the tiles, shows the map's bright top and dark bottom.
    right = img[:, slots[0, -1, 1] + cam.width + 5 :].reshape(-1, 3).astype(int)
    assert np.min(np.linalg.norm(right - hot, axis=1)) < 30
    assert np.min(np.linalg.norm(right - cold, axis=1)) < 30


def test_error_against_checks_shapes(horse):
    verts, faces = horse
    with pytest.raises(MeshseqError, match="frames"):
        render.film_strip([verts[:10]], faces, ground_truth=verts[:5], camera=render.frame_camera(verts, height=20))
    with pytest.raises(MeshseqError, match="vertices"):
        render.film_strip([verts[:2]], faces, ground_truth=verts[:2, :100])


def test_vertex_errors_and_colours():
    a = np.zeros((2, 3, 3))
    b = a.copy()
    b[1, 2] = [3.0, 4.0, 0.0]
    e = render.vertex_errors(a, b)
    np.testing.assert_allclose(e, [[0, 0, 0], [0, 0, 5]])
    c = render.error_colors(e, vmax=5.0)
    assert c.shape == (2, 3, 3) and np.all((c >= 0) & (c <= 1))
    assert c[1, 2].sum() > c[0, 0].sum() + 1.0  # hot is brighter than cold


def test_animation_frames_side_by_side_with_counter(horse):
    verts, faces = horse
    a, b = verts[:6], verts[:4]
    cam = render.frame_camera([a, b], height=50)
    frames = render.animation_frames([a, b], faces, labels=["a", "b"], every=2, camera=cam)
    assert frames.shape[0] == 3  # frames 0, 2, 4
    canvas, slots = render.layout_canvas(1, 2, cam.width, cam.height, col_labels=["a", "b"], header_px=20)
    assert frames.shape[1:] == canvas.shape
    y, x = slots[0, 1]
    # b has 4 frames: at frame 4 it holds its last frame (3), so its tile differs from frame 2's.
    tile = lambda n: frames[n, y : y + cam.height, x : x + cam.width]  # noqa: E731
    assert _foreground(tile(2)).mean() > 0.03
    assert not np.array_equal(frames[0, :20], frames[1, :20])  # the counter changes


# --------------------------------------------------------------------------------------------
# Writers


def test_save_image_and_animations_roundtrip(tmp_path):
    import imageio.v2 as imageio

    img = np.zeros((31, 47, 3), np.uint8)
    img[5:20, 10:30] = [200, 30, 30]
    out = render.save_image(tmp_path / "a.png", img)
    np.testing.assert_array_equal(np.asarray(Image.open(out).convert("RGB")), img)
    with pytest.raises(MeshseqError, match="exists"):
        render.save_image(tmp_path / "a.png", img * 0)
    np.testing.assert_array_equal(np.asarray(Image.open(out).convert("RGB")), img)  # untouched
    render.save_image(tmp_path / "a.png", img * 0, force=True)
    assert np.asarray(Image.open(out)).max() == 0

    frames = np.stack([np.roll(img, 3 * k, axis=1) for k in range(5)])
    gif = render.save_animation(tmp_path / "a.gif", frames, fps=10)
    back = np.asarray(imageio.mimread(gif))[..., :3]
    assert back.shape == frames.shape
    assert np.abs(back.astype(int) - frames).max() < 40  # palette quantisation only
    mp4 = render.save_animation(tmp_path / "a.mp4", frames, fps=10)
    reader = imageio.get_reader(mp4)
    try:
        vid = np.stack([f for f in reader.iter_data()])
        assert reader.get_meta_data()["fps"] == pytest.approx(10)
    finally:
        reader.close()
    assert vid.shape[0] == 5 and vid.shape[1] >= 31 and vid.shape[2] >= 47
    with pytest.raises(MeshseqError, match="extension"):
        render.save_animation(tmp_path / "a.avi", frames)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.gif", "a.mp4", "a.png"]  # no temporaries


# --------------------------------------------------------------------------------------------
# meshseq render


def test_cli_render_png_gif_and_errors(tmp_path, capsys):
    horse_path = str(shared_file("horse-gallop.npz"))
    out = tmp_path / "strip.png"
    assert main(["render", horse_path, "-o", str(out), "--every", "24", "--height", "60"]) == 0
    img = np.asarray(Image.open(out).convert("RGB"))
    assert _foreground(img).mean() > 0.05
    assert "wrote" in capsys.readouterr().out

    # Existing output without --force: one-line error, file unchanged.
    before = out.read_bytes()
    assert main(["render", horse_path, "-o", str(out), "--every", "24"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("meshseq: error:") and "exists" in err and "\n" not in err
    assert out.read_bytes() == before

    # Unknown extension.
    assert main(["render", horse_path, "-o", str(tmp_path / "x.jpg")]) == 2
    err = capsys.readouterr().err.strip()
    assert "extension" in err and "\n" not in err

    # Mismatched connectivity between SEQs: error, nothing written.
    pcow = str(shared_file("pcow.npz"))
    assert main(["render", horse_path, pcow, "-o", str(tmp_path / "two.png")]) == 2
    err = capsys.readouterr().err.strip()
    assert "connectivity" in err and "\n" not in err
    assert main(["render", horse_path, "-o", str(tmp_path / "e.png"), "--error-against", pcow]) == 2
    assert "connectivity" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["strip.png"]

    gif = tmp_path / "a.gif"
    assert main(["render", horse_path, horse_path, "-o", str(gif), "--every", "12", "--height", "40",
                 "--error-against", horse_path, "--labels", "one,two"]) == 0
    with Image.open(gif) as im:
        assert im.n_frames == 4


# --------------------------------------------------------------------------------------------
# Plots


def test_error_vs_horizon_plots_means_in_paper_units():
    errs = {"ours": np.array([[1e-4, 2e-4, 3e-4], [3e-4, 4e-4, 5e-4]]), "zero velocity": np.array([5e-4, 6e-4, 7e-4])}
    fig = plots.error_vs_horizon(errs)
    lines = {ln.get_label(): ln for ln in fig.axes[0].get_lines()}
    np.testing.assert_allclose(lines["ours"].get_ydata(), [2, 3, 4])
    np.testing.assert_allclose(lines["zero velocity"].get_xdata(), [1, 2, 3])
    assert "10^{-4}" in fig.axes[0].get_ylabel()
    assert plots.figure_to_array(fig).shape[2] == 3
    with pytest.raises(MeshseqError):
        plots.error_vs_horizon({})


def test_feature_change_values():
    x = np.ones((4, 5, 9))
    np.testing.assert_allclose(plots.feature_change(x), 0.0)
    ramp = np.ones((3, 2, 9)) * np.array([1.0, 2.0, 4.0])[:, None, None]
    np.testing.assert_allclose(plots.feature_change(ramp), [1.0, 1.0])  # |2-1|/1, |4-2|/2
    batched = np.stack([ramp, np.ones((3, 2, 9))])
    np.testing.assert_allclose(plots.feature_change(batched), [0.5, 0.5])
    fig = plots.feature_change_curve({"ramp": ramp, "curve": np.array([0.1, 0.2])})
    ys = [ln.get_ydata() for ln in fig.axes[0].get_lines()]
    np.testing.assert_allclose(ys[0], [1.0, 1.0])
    with pytest.raises(MeshseqError):
        plots.feature_change(np.ones((1, 3, 9)))


def test_training_curves_from_a_run_csv(tmp_path):
    csv = tmp_path / "metrics.csv"
    csv.write_text("iteration,loss,rec,kl\n0,10,8,\n10,5,4,0.5\n20,2.5,2,0.25\n")
    m = plots.read_metrics_csv(csv)
    np.testing.assert_allclose(m["iteration"], [0, 10, 20])
    assert np.isnan(m["kl"][0])
    fig = plots.training_curves(m)
    ax = fig.axes[0]
    assert ax.get_yscale() == "log"
    lines = {ln.get_label(): ln for ln in ax.get_lines()}
    assert set(lines) == {"loss", "rec", "kl"}
    np.testing.assert_allclose(lines["kl"].get_xdata(), [10, 20])  # NaN rows skipped
    out = plots.save_figure(fig, tmp_path / "curves.png")
    assert _foreground(np.asarray(Image.open(out).convert("RGB"))).mean() > 0.01
    with pytest.raises(MeshseqError, match="exists"):
        plots.save_figure(fig, tmp_path / "curves.png")

    bad = tmp_path / "bad.csv"
    bad.write_text("iteration,loss\n0,1\n1,oops\n")
    with pytest.raises(MeshseqError, match=r"line 3.*'loss'.*oops"):
        plots.read_metrics_csv(bad)
    (tmp_path / "noit.csv").write_text("step,loss\n0,1\n")
    with pytest.raises(MeshseqError, match="iteration"):
        plots.read_metrics_csv(tmp_path / "noit.csv")
    with pytest.raises(MeshseqError, match="extension"):
        plots.save_figure(fig, tmp_path / "curves.bmp")


def test_no_warnings_when_rendering_normally(horse):
    verts, faces = horse
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        render.film_strip([verts[:2]], faces, every=1, tile_height=40)


def test_cli_render_frames_window_labels_true_frame_numbers(tmp_path, capsys, horse):
    verts, faces = horse
    out = tmp_path / "w.png"
    horse_path = str(shared_file("horse-gallop.npz"))
    assert main(["render", horse_path, "-o", str(out), "--frames", "10:", "--every", "19", "--height", "50",
                 "--labels", "h"]) == 0
    got = np.asarray(Image.open(out).convert("RGB"))
    expected = render.film_strip([verts[10:]], faces, labels=["h"], every=19, tile_height=50, first_frame=10)
    np.testing.assert_array_equal(got, expected)  # frames 10 and 29, labelled so
    other = render.film_strip([verts[10:]], faces, labels=["h"], every=19, tile_height=50)
    assert not np.array_equal(other, expected)  # the labels differ
    assert main(["render", horse_path, "-o", str(tmp_path / "x.png"), "--frames", "7"]) == 2
    assert "--frames" in capsys.readouterr().err
    assert main(["render", horse_path, "-o", str(tmp_path / "x.png"), "--frames", "60:"]) == 2
    assert "no frames" in capsys.readouterr().err
    assert not (tmp_path / "x.png").exists()


def test_up_axis_option_matches_a_rotated_copy(horse):
    verts, faces = horse
    v = verts[:1]
    z_up = np.stack([v[..., 0], -v[..., 2], v[..., 1]], axis=-1)  # y-up data turned z-up
    a = render.film_strip([v], faces, every=1, tile_height=60)
    b = render.film_strip([z_up], faces, every=1, tile_height=60, up="z")
    assert a.shape == b.shape
    assert np.abs(a.astype(int) - b.astype(int)).mean() < 1.0
    c = render.film_strip([z_up], faces, every=1, tile_height=60)  # wrong up: a different picture
    assert c.shape != a.shape or np.abs(a.astype(int) - c.astype(int)).mean() > 3.0
