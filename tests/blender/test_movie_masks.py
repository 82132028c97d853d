"""A mask that is a movie is read at the frame Blender's image user would show (frames,
start, offset, cyclic on the camera's list item), decoded by Blender's own FFmpeg.

The movies are made here: discs drawn with numpy, written as PNG files and encoded
with Blender's own FFmpeg output (PNG in QuickTime: lossless), so each frame's
expected mask is the disc drawn for it."""

import os
import threading

import bpy
import numpy as np
import pytest

from fixtures.blender.objects import mask_image
from fixtures.blender.scenes import two_camera_scene
from multiscale_camera.adapters.masks import (
    ANIMATED_MASK,
    FRAME_NOT_LOADED,
    MOVIE_UNREADABLE,
    MaskFrames,
    mask_from_image,
)
from multiscale_camera.adapters.movies import movie_frame
from multiscale_camera.adapters.scene import rig_from_scene
from multiscale_camera.render.fields import SERVICE
from multiscale_camera.ui.panels import animated_mask_wording, draw_camera_settings
from tests.blender.test_animation import REGISTER
from tests.exr import read_passes

W, H = 48, 36
# Frame k's disc (k = 1..4): radius 6 px about (CENTRES[k - 1], 17.5), in pixel centres.
CENTRES = (12.5, 20.5, 28.5, 36.5)
RADIUS = 6.0


def disc(k):
    """(H, W) bool, row 0 at the top: frame k's disc (k counted from 1)."""
    rows, cols = np.mgrid[0:H, 0:W] + 0.5
    return (cols - CENTRES[k - 1]) ** 2 + (rows - 18.0) ** 2 <= RADIUS**2


def write_movie(folder, name="discs.mov"):
    """Frames 1-4 (``disc``) encoded by Blender's FFmpeg output into ``folder/name``
    through a temporary sequencer scene (removed with its images); the movie's path."""
    for k in range(1, len(CENTRES) + 1):
        rgba = np.zeros((H, W, 4), np.float32)
        rgba[..., 3] = 1.0
        rgba[disc(k), :3] = 1.0
        still = bpy.data.images.new(f"disc {k}", W, H)
        still.pixels.foreach_set(rgba[::-1].ravel())
        still.filepath_raw = str(folder / f"disc_{k:04d}.png")
        still.file_format = "PNG"
        still.save()
        bpy.data.images.remove(still)
    scene = bpy.data.scenes.new("encode")
    render = scene.render
    render.resolution_x, render.resolution_y, render.resolution_percentage = W, H, 100
    scene.frame_start, scene.frame_end = 1, len(CENTRES)
    scene.view_settings.view_transform = "Standard"  # white stays 1
    editor = scene.sequence_editor_create()
    strip = editor.strips.new_image("discs", str(folder / "disc_0001.png"), 1, 1)
    for k in range(2, len(CENTRES) + 1):
        strip.elements.append(f"disc_{k:04d}.png")
    settings = render.image_settings
    settings.media_type, settings.file_format, settings.color_mode = "VIDEO", "FFMPEG", "RGB"
    render.ffmpeg.format, render.ffmpeg.codec = "QUICKTIME", "PNG"
    render.filepath = str(folder / name)
    render.use_file_extension = False
    with bpy.context.temp_override(scene=scene):
        bpy.ops.render.render(animation=True, scene=scene.name)
    bpy.data.scenes.remove(scene)
    return folder / name


@pytest.fixture(scope="module")
def movie(tmp_path_factory):
    return write_movie(tmp_path_factory.mktemp("movie"))


def blend_data():
    """How many of each kind of data-block the file holds."""
    kinds = ("images", "node_groups", "meshes", "objects", "scenes")
    return {k: len(getattr(bpy.data, k)) for k in kinds}


def test_each_movie_frame_decodes_to_the_disc_drawn_for_it(movie):
    before = blend_data()
    for number, k in ((-3, 1), (0, 1), (1, 1), (2, 2), (3, 3), (4, 4), (5, 4), (99, 4)):
        rgba = movie_frame(str(movie), number)
        assert rgba.shape == (H, W, 4)
        np.testing.assert_array_equal(rgba[..., :3] >= 0.5, np.repeat(disc(k)[..., None], 3, -1))
        assert set(np.unique(rgba[..., :3])) == {0.0, 1.0}, number  # lossless
    assert blend_data() == before  # the temporary data is gone


@pytest.fixture
def scene(empty_scene, movie):
    """The two-camera scene whose camera 2 (the smallest scale: it keeps its pixels)
    has the movie as its mask."""
    two_camera_scene(empty_scene, W, H)
    empty_scene.multiscale.cameras[1].mask = bpy.data.images.load(str(movie))
    return empty_scene


def read_at(scene, frame):
    """Camera 2's mask and the field's cache key at ``frame``."""
    scene.frame_set(frame)
    depsgraph = bpy.context.evaluated_depsgraph_get()
    rig = rig_from_scene(depsgraph.scene, depsgraph, frames=SERVICE.mask_frames)
    return rig.masks[1], SERVICE.request(depsgraph.scene, rig=rig).key


def shown(scene, frame):
    """Which disc (1..4) camera 2's mask is at ``frame`` (0: none of them)."""
    mask = read_at(scene, frame)[0]
    return next((k for k in range(1, 5) if np.array_equal(mask, disc(k))), 0)


def test_a_movie_mask_plays_its_own_length_from_frame_1(scene):
    item = scene.multiscale.cameras[1]
    assert item.mask.source == "MOVIE"
    assert item.mask_frames == 4  # set when the movie became the mask
    assert [shown(scene, f) for f in range(-1, 8)] == [1, 1, 1, 2, 3, 4, 4, 4, 4]
    keys = [read_at(scene, f)[1] for f in (1, 2, 5, 6)]
    assert keys[0] != keys[1] and keys[2] == keys[3]  # the key follows the frame's pixels
    notices = rig_from_scene(scene, frames=SERVICE.mask_frames).notices
    assert not any("movie" in n for n in notices), notices


def test_start_offset_and_cyclic_choose_the_movie_frame(scene):
    item = scene.multiscale.cameras[1]
    item.mask_frame_start = 3
    assert [shown(scene, f) for f in (2, 3, 4, 6, 9)] == [1, 1, 2, 4, 4]
    item.mask_frame_start, item.mask_frame_offset = 1, 2
    assert [shown(scene, f) for f in (1, 2, 3)] == [3, 4, 4]  # frame 1 shows number 3
    item.mask_frame_offset, item.mask_cyclic = 0, True
    assert [shown(scene, f) for f in (1, 4, 5, 6, 9, 0)] == [1, 4, 1, 2, 1, 4]
    item.mask_frames = 2  # plays the movie's first two frames
    assert [shown(scene, f) for f in (1, 2, 3, 4)] == [1, 2, 1, 2]


def test_the_frame_read_is_the_one_blenders_image_user_shows(scene):
    """The movie in an image texture node (auto refresh) of a material: the frame its
    image user shows at each scene frame is the one camera 2's mask reads."""
    item = scene.multiscale.cameras[1]
    material = bpy.data.materials.new("M")
    material.use_nodes = True
    node = material.node_tree.nodes.new("ShaderNodeTexImage")
    node.image = item.mask
    mesh = bpy.data.meshes.new("me")
    mesh.materials.append(material)
    scene.collection.objects.link(bpy.data.objects.new("ob", mesh))
    user = node.image_user
    user.use_auto_refresh = True
    for frames, start, offset, cyclic in ((4, 1, 0, False), (3, 2, 1, True), (4, -2, -1, False)):
        user.frame_duration, user.frame_start = frames, start
        user.frame_offset, user.use_cyclic = offset, cyclic
        item.mask_frames, item.mask_frame_start = frames, start
        item.mask_frame_offset, item.mask_cyclic = offset, cyclic
        for frame in range(-3, 10):
            got = shown(scene, frame)
            depsgraph = bpy.context.evaluated_depsgraph_get()
            evaluated = material.evaluated_get(depsgraph).node_tree.nodes[node.name]
            number = evaluated.image_user.frame_current
            assert got == min(max(number, 1), 4), (frames, start, offset, cyclic, frame)


@pytest.mark.slow
def test_an_animation_render_reads_the_movie_mask_of_each_frame(scene, tmp_path):
    """Each frame of ``render(animation=True)`` equals a still render whose camera 2
    mask is a still image of that frame's disc."""
    scene.frame_start, scene.frame_end = 1, 3
    scene.render.image_settings.media_type = "MULTI_LAYER_IMAGE"
    scene.render.filepath = str(tmp_path / "anim_####")
    bpy.ops.render.render(animation=True)
    item = scene.multiscale.cameras[1]
    movie_mask = item.mask
    membership = {}
    for frame in (1, 2, 3):
        passes = read_passes(tmp_path / f"anim_{frame:04d}.exr")
        membership[frame] = passes["Membership"][..., 0]
        item.mask = mask_image(f"disc {frame}", disc(frame))
        scene.frame_set(frame)
        scene.render.filepath = str(tmp_path / f"still_{frame}.exr")
        bpy.ops.render.render(write_still=True)
        still = read_passes(tmp_path / f"still_{frame}.exr")
        for name in ("Combined", "Membership", "IndexOB"):
            gap = np.abs(passes[name] - still[name]).max()
            assert gap <= 1e-3, (frame, name, gap)
        item.mask = movie_mask
        row, col = 17, int(CENTRES[frame - 1])
        assert membership[frame][row, col] == pytest.approx(2.0)
    assert not np.array_equal(membership[1], membership[3])


class Recorder:
    """Stands in for a panel's UILayout: records label texts and props drawn."""

    def __init__(self, calls):
        self.calls = calls

    def prop(self, _data, name, **_kw):
        self.calls.append(name)

    def label(self, text="", **_kw):
        self.calls.append(text)

    def operator(self, *_a, **_kw):
        return type("Props", (), {})()

    def __getattr__(self, _name):  # row, column, template_ID ...
        return lambda *_a, **_kw: Recorder(self.calls)


@pytest.mark.slow
@pytest.mark.e2e
def test_command_line_animation_reads_the_movie_mask_of_each_frame(scene, tmp_path, run_blender):
    """``blender -b file.blend -s 1 -e 3 -a``, as render farms run it, with the movie
    next to the .blend (a relative path, as on shared storage): each frame equals a
    still render whose camera 2 mask is a still image of that frame's disc."""
    movie = write_movie(tmp_path, "discs.mov")
    scene.multiscale.cameras[1].mask = bpy.data.images.load(str(movie))
    scene.render.image_settings.media_type = "MULTI_LAYER_IMAGE"
    blend = tmp_path / "movie_mask.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend), relative_remap=True)
    assert scene.multiscale.cameras[1].mask.filepath == "//discs.mov"
    out = tmp_path / "out"
    proc = run_blender(
        ["-b", blend, "--python-exit-code", "1", "--python-expr", REGISTER]
        + ["-o", out / "frame_####", "-s", "1", "-e", "3", "-a"]
    )
    assert "cannot read" not in proc.stdout and "not loaded" not in proc.stdout
    item = scene.multiscale.cameras[1]
    for frame in (1, 2, 3):
        passes = read_passes(out / f"frame_{frame:04d}.exr")
        item.mask = mask_image(f"disc {frame}", disc(frame))
        scene.frame_set(frame)
        scene.render.filepath = str(tmp_path / f"still_{frame}.exr")
        bpy.ops.render.render(write_still=True)
        still = read_passes(tmp_path / f"still_{frame}.exr")
        for name in ("Combined", "Membership", "IndexOB"):
            gap = np.abs(passes[name] - still[name]).max()
            assert gap <= 1e-3, (frame, name, gap)


def test_the_camera_settings_show_the_movies_frames_and_mapping(scene):
    calls = []
    draw_camera_settings(Recorder(calls), bpy.context, scene.multiscale.cameras[1])
    heading = "Mask movie (4 frames), read at each frame:"
    assert calls[calls.index(heading) + 1 : calls.index(heading) + 5] == [
        "mask_frames",
        "mask_frame_start",
        "mask_frame_offset",
        "mask_cyclic",
    ]


def test_the_panel_says_what_the_animated_mask_is(scene, movie, tmp_path):
    item = scene.multiscale.cameras[1]
    assert animated_mask_wording(item) == ("Mask movie (4 frames), read at each frame:", "")
    item.mask_frames = 10
    assert animated_mask_wording(item) == (
        "Mask movie (4 frames), read at each frame:",
        "The movie has 4 frames; Frames plays 10",
    )
    bad = tmp_path / "not_a_movie.mov"
    bad.write_bytes(b"not a video at all" * 100)
    item.mask = bpy.data.images.load(str(bad))
    assert animated_mask_wording(item) == (
        "Mask movie Blender cannot play:",
        "file missing or not a video; reads empty",
    )
    item.mask = mask_image("still", disc(1))
    assert animated_mask_wording(item) is None
    item.mask = bpy.data.images.load(str(movie.parent / "disc_0001.png"))
    item.mask.source = "SEQUENCE"
    assert animated_mask_wording(item) == ("Mask sequence, read at each frame:", "")


@pytest.mark.parametrize("spoil", ["missing", "unreadable"])
def test_a_missing_or_unreadable_movie_is_said_and_its_file_kept(scene, tmp_path, spoil):
    path = write_movie(tmp_path, "spoilt.mov")
    item = scene.multiscale.cameras[0]
    item.mask = bpy.data.images.load(str(path))
    if spoil == "missing":
        os.remove(path)
    else:
        path.write_bytes(b"\0" * 4096)
    kept = None if spoil == "missing" else path.read_bytes()
    before = blend_data()
    scene.frame_set(2)
    rig = rig_from_scene(scene, frames=MaskFrames())
    said = MOVIE_UNREADABLE.format(name=item.mask.name, path=str(path))
    assert said in rig.notices, rig.notices
    assert not rig.masks[0].any()
    assert blend_data() == before  # nothing left behind, nothing of the user's removed
    assert item.mask is not None and item.mask.filepath == str(path)
    if kept is not None:
        assert path.read_bytes() == kept


def test_a_movie_read_without_a_frame_number_says_so(scene):
    image = scene.multiscale.cameras[1].mask
    mask, notices = mask_from_image(image, W, H)
    assert notices == [ANIMATED_MASK.format(name=image.name, kind="a movie")]
    assert not mask.any()


def test_a_movie_frame_first_needed_off_the_main_thread_is_said_not_loaded(scene):
    """Camera 1 has the movie (camera 2 a corner of the frame: its mask is never empty,
    which the rig would refuse for the last camera)."""
    frames = MaskFrames()
    item, last = scene.multiscale.cameras
    item.mask = last.mask
    corner = np.zeros((H, W), bool)
    corner[:4, :4] = True
    last.mask = mask_image("corner", corner)
    scene.frame_set(3)
    got = {}

    def read():
        got["rig"] = rig_from_scene(scene, frames=frames)

    worker = threading.Thread(target=read)
    worker.start()
    worker.join()
    path = bpy.path.abspath(item.mask.filepath)
    said = FRAME_NOT_LOADED.format(name=item.mask.name, number=3, path=path)
    assert said in got["rig"].notices
    rig_from_scene(scene, frames=frames)  # the main thread reads it; then a thread can
    worker = threading.Thread(target=read)
    worker.start()
    worker.join()
    np.testing.assert_array_equal(got["rig"].masks[0], disc(3))


def test_reading_a_movie_mask_again_changes_no_blender_data(scene):
    frames = MaskFrames()
    rig_from_scene(scene, frames=frames)  # the first read decodes frame 1 once
    bpy.context.evaluated_depsgraph_get()
    before = blend_data()
    updates = []

    def seen(_scene, depsgraph):
        updates.extend(u.id.name for u in depsgraph.updates)

    bpy.app.handlers.depsgraph_update_post.append(seen)
    try:
        for _ in range(2):
            rig_from_scene(scene, frames=frames)
            bpy.context.evaluated_depsgraph_get()
    finally:
        bpy.app.handlers.depsgraph_update_post.remove(seen)
    assert updates == []
    assert blend_data() == before
