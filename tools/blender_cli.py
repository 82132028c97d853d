"""Blender's command line, emulated on the bpy wheel (run it through tools/blender).

As in Blender, the settings flags act first wherever they stand (``-b``/``--background``,
``--factory-startup``, ``-v``/``--version``), then the others act in order:

    FILE.blend                  open it (wm.open_mainfile); on failure exit 1
    --addons a,b                enable add-ons, as Blender does
    -P/--python FILE            run a script (__name__ == "__main__", __file__ set)
    --python-expr CODE          run code
    --python-exit-code N        from here on, a failing script or expression exits with N
                                (0, the default: print the traceback and go on)
    -E/--engine ENGINE          set the scene's render engine
    -o/--render-output PATH     set the render output path ('//' = blend folder, '#' = frame)
    -F/--render-format FORMAT   set the output format (PNG, OPEN_EXR_MULTILAYER, FFMPEG, ...)
    -f/--render-frame N[,M..]   render frames and save them to the output path (N..M ranges);
                                a render that fails saves nothing and exits 1
    -s/--frame-start N          set the scene's first frame (+N/-N: relative to it)
    -e/--frame-end N            set the scene's last frame (+N/-N: relative to it)
    -j/--frame-jump N           set the frame step (at least 1)
    -a/--render-anim            render frames start..end (every step-th) and save them;
                                a render that fails saves nothing and exits 1

Rendering is Blender's own (``render.render(animation=True)``, the RE_RenderAnim of the
bpy wheel), so its output naming ('#' runs become the zero-padded frame number, else
the number is appended), its placeholders (Output > Placeholders: an empty file written
before a frame renders) and its no-overwrite (Output > Overwrite off: frames whose file
exists are skipped) are Blender's. As in Blender, -s and -e write the range as given:
a start after the end renders nothing (the scene's own properties would move the other
end along; the emulator keeps the range it was given for -a and -f's relative frames).
    --                          end of Blender's arguments; scripts read the rest

``sys.argv`` is ``["blender", *arguments]``. Without ``--factory-startup`` the user's
preferences and startup file (under $BLENDER_USER_RESOURCES, if set) are loaded.
The process is always in background mode: the wheel has no window.

Ctrl-C (SIGINT) acts as in `blender -b` (``emulate_ctrl_c``): it sets Blender's break
flag, which renders and Cycles poll, and says so; a second one exits 2.
"""

import builtins
import ctypes
import mmap
import os
import signal
import struct
import sys
import threading
import traceback

SETTINGS = {"-b", "--background", "--factory-startup", "-v", "--version"}
ALIASES = {
    "-P": "--python",
    "-E": "--engine",
    "-o": "--render-output",
    "-F": "--render-format",
    "-f": "--render-frame",
    "-s": "--frame-start",
    "-e": "--frame-end",
    "-j": "--frame-jump",
    "-a": "--render-anim",
}
NO_VALUE = {"--render-anim"}
# -F's names that differ from the file_format property's (BKE_imtype_from_arg), and the
# media type Blender 5 sets with them (BKE_image_format_set).
FORMAT_NAMES = {"TGA": "TARGA", "RAWTGA": "TARGA_RAW", "JP2": "JPEG2000"}
MEDIA_TYPES = {"OPEN_EXR_MULTILAYER": "MULTI_LAYER_IMAGE", "FFMPEG": "VIDEO"}
# Blender's frame limits (MINAFRAME, MAXFRAME): -s, -e and -f clamp to them.
MIN_FRAME, MAX_FRAME = -1048574, 1048574
WITH_VALUE = {
    "--addons",
    "--python",
    "--python-expr",
    "--python-exit-code",
    "--engine",
    "--render-output",
    "--render-format",
    "--render-frame",
    "--frame-start",
    "--frame-end",
    "--frame-jump",
}


class UsageError(Exception):
    pass


def parse(args):
    """Split Blender's own arguments into settings and (flag, value) actions, in order."""
    settings, actions = set(), []
    args = iter(args)
    for arg in args:
        if arg == "--":
            break
        if arg in SETTINGS:
            settings.add(arg)
            continue
        flag = ALIASES.get(arg, arg)
        if flag in WITH_VALUE:
            value = next(args, None)
            if value is None:
                raise UsageError(f"{arg} needs a value")
            actions.append((flag, value))
        elif flag in NO_VALUE:
            actions.append((flag, None))
        elif arg.startswith("-"):
            raise UsageError(f"unknown argument {arg}")
        else:
            actions.append(("blend", arg))
    return settings, actions


def print_version(bpy):
    app = bpy.app
    print(f"Blender {app.version_string}")
    print(f"\tbuild date: {app.build_date.decode()}")
    print(f"\tbuild hash: {app.build_hash.decode()}")
    print(f"\tbuild branch: {app.build_branch.decode()}")
    print(f"\tbuild platform: {app.build_platform.decode()}")
    print("\t(bpy module, emulated command line)")


def load_startup(bpy, factory):
    if factory:
        bpy.ops.wm.read_homefile(use_factory_startup=True)
        return
    userpref = os.path.join(bpy.utils.user_resource("CONFIG"), "userpref.blend")
    if os.path.isfile(userpref):
        bpy.ops.wm.read_userpref()
    bpy.ops.wm.read_homefile()


def run_python(code, filename):
    """Run code as Blender does; return False (after printing the traceback) if it raised."""
    namespace = {"__name__": "__main__", "__builtins__": builtins}
    if filename != "<string>":
        namespace["__file__"] = filename
    try:
        exec(compile(code, filename, "exec"), namespace)
    except Exception as ex:
        traceback.print_exception(ex.with_traceback(ex.__traceback__.tb_next))  # from the code on
        return False
    return True


def relative(text, plus, minus):
    """Blender's frame argument: 'N', '+N' (``plus`` + N) or '-N' (``minus`` - N + 1),
    clamped to Blender's frame limits."""
    if text.startswith("+"):
        value = plus + int(text[1:])
    elif text.startswith("-"):
        value = minus - int(text[1:]) + 1
    else:
        value = int(text)
    return min(max(value, MIN_FRAME), MAX_FRAME)


def frames(spec, start=1, end=250):
    """'3', '1,5', '2..4' -> [3], [1, 5], [2, 3, 4]; '+N' counts from ``start``, '-N'
    back from ``end`` (as `blender -f`)."""
    result = []
    for part in spec.split(","):
        first, _, last = part.partition("..")
        first = relative(first, start, end)
        result += range(first, (relative(last, start, end) if last else first) + 1)
    return result


class FrameRange:
    """The scene's frame range as -s, -e and -j gave it (Blender writes them as given,
    a start after the end included); None: the scene's own."""

    def __init__(self):
        self.start = self.end = None

    def of(self, scene):
        start = scene.frame_start if self.start is None else self.start
        end = scene.frame_end if self.end is None else self.end
        return start, end

    def set(self, scene, which, text):
        start, end = self.of(scene)
        if which == "start":
            self.start = start = relative(text, start, start - 1)
        else:
            self.end = end = relative(text, end, end - 1)
        # the scene's properties keep start <= end by moving the other end along
        scene.frame_start = start
        if end >= start:
            scene.frame_end = end


def render_range(bpy, first, last):
    """Render and save frames ``first .. last`` (every frame_step-th) as Blender's
    RE_RenderAnim does: placeholders and no-overwrite included. Returns False when a
    render failed (the engine reported an error: Blender saves nothing and exits
    non-zero), after printing Blender's message."""
    if first > last:
        return True
    scene = bpy.context.scene
    start, end = scene.frame_start, scene.frame_end
    try:
        # Setting the start moves the end along (and the reverse), so this order is safe.
        scene.frame_start, scene.frame_end = first, first
        scene.frame_end = last
        bpy.ops.render.render(animation=True)
    except RuntimeError as ex:
        print(f"\n{str(ex).strip()}", file=sys.stderr)
        return False
    finally:
        scene.frame_start, scene.frame_end = start, end
    return True


def render_frames(bpy, spec, span):
    """Render and save each frame as `blender -f` does (frame number in the file name);
    False when a render failed (``render_range``)."""
    scene = bpy.context.scene
    step = scene.frame_step
    try:
        scene.frame_step = 1  # -f renders every frame it names
        for frame in frames(spec, *span.of(scene)):
            if not render_range(bpy, frame, frame):
                return False
    finally:
        scene.frame_step = step
    return True


FRAME_FLAGS = {
    "--frame-start": "-s / --frame-start",
    "--frame-end": "-e / --frame-end",
    "--frame-jump": "-j / --frame-jump",
}


def set_frames(scene, span, flag, value):
    """-s, -e or -j; ValueError when ``value`` is not a number (Blender says so and goes
    on)."""
    if flag == "--frame-jump":
        scene.frame_step = min(max(int(value), 1), MAX_FRAME)
    else:
        span.set(scene, "start" if flag == "--frame-start" else "end", value)


def set_format(scene, name):
    """-F: the output format by Blender's argument name; False when unknown."""
    settings = scene.render.image_settings
    file_format = FORMAT_NAMES.get(name, name)
    media = getattr(settings, "media_type", None)
    if media is not None:  # Blender 5: the kind of output first
        settings.media_type = MEDIA_TYPES.get(file_format, "IMAGE")
    try:
        settings.file_format = file_format
    except TypeError:
        if media is not None:
            settings.media_type = media  # unknown: the output stays as it was
        return False
    return True


# Blender's ``Global`` (BKE_global.hh) in the bpy 5.0.1 wheel: its size, and the offsets
# of ``is_break`` and of ``background``, the next member (1 in a background process).
GLOBAL_SIZE, IS_BREAK, BACKGROUND = 3552, 3104, 3105


def global_address(library):
    """The address of Blender's ``G`` in this process, from ``library``'s (the wheel's
    bpy/__init__.so) symbol table and where it is loaded, or None when either is missing
    or ``G`` is not the ``Global`` of ``GLOBAL_SIZE`` bytes this emulation knows."""
    try:
        with open(library, "rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as m:
            shoff = struct.unpack_from("<Q", m, 0x28)[0]
            shentsize, shnum = struct.unpack_from("<HH", m, 0x3A)
            sections = [
                struct.unpack_from("<IIQQQQIIQQ", m, shoff + i * shentsize) for i in range(shnum)
            ]
            symtab = next(s for s in sections if s[1] == 2)  # SHT_SYMTAB
            strtab = sections[symtab[6]]
            name = m.find(b"\0G\0", strtab[4], strtab[4] + strtab[5]) + 1 - strtab[4]
            value = None
            for i in range(symtab[5] // 24):  # Elf64_Sym: name, info, other, shndx, value, size
                st_name, st_info, _o, _n, st_value, st_size = struct.unpack_from(
                    "<IBBHQQ", m, symtab[4] + 24 * i
                )
                if st_name == name and st_info & 0xF == 1 and st_size == GLOBAL_SIZE:
                    value = st_value
                    break
    except (OSError, ValueError, StopIteration, struct.error):
        return None
    if value is None:
        return None
    for line in open("/proc/self/maps"):
        parts = line.split()
        if len(parts) >= 6 and parts[1].endswith("p") and int(parts[2], 16) == 0:
            if os.path.realpath(parts[5]) == os.path.realpath(library):
                return int(parts[0].split("-")[0], 16) + value
    return None


def emulate_ctrl_c(bpy):
    """Blender's Ctrl-C in background mode (creator_signals.cc, sig_handle_blender_esc:
    set ``G.is_break``, print "Sent an internal break event", exit 2 on a second one),
    which the wheel lacks (SIGINT raises KeyboardInterrupt there). A Python handler runs
    only when the main thread runs Python, not during a render in C; so the handler
    here is Python's own C handler with ``signal.set_wakeup_fd``, and a thread woken by
    it writes ``G.is_break`` (found by ``global_address``) at once, while this handler is
    SIGINT's (an add-on's own handler, while it holds, hears Ctrl-C alone). Without
    ``G`` Ctrl-C stays Python's and a warning says so."""
    library = os.path.join(os.path.dirname(bpy.__file__).split(os.sep + "5.0" + os.sep)[0])
    address = global_address(os.path.join(library, "__init__.so"))
    if address is None or ctypes.c_ubyte.from_address(address + BACKGROUND).value != 1:
        print(
            "tools/blender: Blender's G not found: Ctrl-C raises KeyboardInterrupt", file=sys.stderr
        )
        return
    is_break = ctypes.c_bool.from_address(address + IS_BREAK)

    def blender_esc(_signum, _frame):  # the thread does Blender's work
        pass

    read, write = os.pipe()
    os.set_blocking(write, False)
    signal.signal(signal.SIGINT, blender_esc)
    signal.set_wakeup_fd(write, warn_on_full_buffer=False)

    def watch():
        breaks = 0
        while True:
            for signum in os.read(read, 64):
                if signum != signal.SIGINT or signal.getsignal(signal.SIGINT) is not blender_esc:
                    continue
                is_break.value = True
                if breaks:
                    print("\nBlender killed", flush=True)
                    os._exit(2)
                print("\nSent an internal break event. Press ^C again to kill Blender", flush=True)
                breaks += 1

    threading.Thread(target=watch, name="blender-esc", daemon=True).start()


def main(args):
    try:
        settings, actions = parse(args)
    except UsageError as ex:
        print(f"Error: {ex}", file=sys.stderr)
        return 1

    sys.argv = ["blender", *args]
    import bpy  # after sys.argv, so add-ons see Blender's arguments

    if settings & {"-v", "--version"}:
        print_version(bpy)
        return 0
    load_startup(bpy, factory="--factory-startup" in settings)
    emulate_ctrl_c(bpy)

    exit_code_on_error = 0
    span = FrameRange()
    for flag, value in actions:
        ok = True
        if flag == "blend":
            try:
                bpy.ops.wm.open_mainfile(filepath=os.path.abspath(value))
            except RuntimeError:
                print(f"Error: file could not be loaded, exiting! {value}", file=sys.stderr)
                return 1
            span = FrameRange()
        elif flag == "--addons":
            from _bpy_internal.addons.cli import set_from_cli

            set_from_cli(value)
        elif flag == "--python":
            path = os.path.abspath(value)
            try:
                with open(path, "rb") as f:
                    ok = run_python(f.read(), path)
            except OSError as ex:
                print(f"Error: {ex}", file=sys.stderr)
                ok = False
        elif flag == "--python-expr":
            ok = run_python(value, "<string>")
        elif flag == "--python-exit-code":
            exit_code_on_error = int(value)
        elif flag == "--engine":
            try:
                bpy.context.scene.render.engine = value
            except TypeError:
                print(f"\nError: engine not found '{value}'", file=sys.stderr)
                return 1
        elif flag == "--render-output":
            bpy.context.scene.render.filepath = value
        elif flag == "--render-format":
            if not set_format(bpy.context.scene, value):
                print(
                    "\nError: Format from '-F / --render-format' not known or not compiled in "
                    "this release.",
                    file=sys.stderr,
                )
        elif flag == "--render-frame":
            if not render_frames(bpy, value, span):
                return 1
        elif flag in ("--frame-start", "--frame-end", "--frame-jump"):
            try:
                set_frames(bpy.context.scene, span, flag, value)
            except ValueError:
                print(f"\nError: not a number '{FRAME_FLAGS[flag]} {value}'.", file=sys.stderr)
        elif flag == "--render-anim":
            if not render_range(bpy, *span.of(bpy.context.scene)):
                return 1
        if not ok and exit_code_on_error:
            print(f"\nError: script failed, {flag} '{value}', exiting.", file=sys.stderr)
            return exit_code_on_error
    return 0


if __name__ == "__main__":
    # Blender's scripts do not see this file's folder on sys.path.
    if sys.path and sys.path[0] == os.path.dirname(os.path.abspath(__file__)):
        del sys.path[0]
    sys.exit(main(sys.argv[1:]))
