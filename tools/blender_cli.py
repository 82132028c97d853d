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
    -f/--render-frame N[,M..]   render frames and save them to the output path (N..M ranges);
                                a render that fails saves nothing and exits 1
    --                          end of Blender's arguments; scripts read the rest

``sys.argv`` is ``["blender", *arguments]``. Without ``--factory-startup`` the user's
preferences and startup file (under $BLENDER_USER_RESOURCES, if set) are loaded.
The process is always in background mode: the wheel has no window.
"""

import builtins
import os
import sys
import traceback

SETTINGS = {"-b", "--background", "--factory-startup", "-v", "--version"}
ALIASES = {"-P": "--python", "-E": "--engine", "-o": "--render-output", "-f": "--render-frame"}
WITH_VALUE = {
    "--addons",
    "--python",
    "--python-expr",
    "--python-exit-code",
    "--engine",
    "--render-output",
    "--render-frame",
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


def frames(spec):
    """'3', '1,5', '2..4' -> [3], [1, 5], [2, 3, 4]."""
    result = []
    for part in spec.split(","):
        first, _, last = part.partition("..")
        result += range(int(first), int(last or first) + 1)
    return result


def render_frames(bpy, spec):
    """Render and save each frame as `blender -f` does (frame number in the file name).
    Returns False when a render failed (the engine reported an error: Blender saves
    nothing and exits non-zero), after printing Blender's message."""
    scene = bpy.context.scene
    start, end = scene.frame_start, scene.frame_end
    try:
        for frame in frames(spec):
            # Setting the start moves the end along (and the reverse), so this order is safe.
            scene.frame_start, scene.frame_end = frame, frame
            bpy.ops.render.render(animation=True)
    except RuntimeError as ex:
        print(f"\n{str(ex).strip()}", file=sys.stderr)
        return False
    finally:
        scene.frame_start, scene.frame_end = start, end
    return True


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

    exit_code_on_error = 0
    for flag, value in actions:
        ok = True
        if flag == "blend":
            try:
                bpy.ops.wm.open_mainfile(filepath=os.path.abspath(value))
            except RuntimeError:
                print(f"Error: file could not be loaded, exiting! {value}", file=sys.stderr)
                return 1
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
        elif flag == "--render-frame":
            if not render_frames(bpy, value):
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
