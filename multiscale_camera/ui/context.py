"""What the operators and panels read from Blender's context, in one place."""


def settings_of(context):
    """The scene's ``scene.multiscale`` settings."""
    return context.scene.multiscale


def evaluated_scene(context):
    """The scene as the depsgraph evaluates it: object matrices up to date."""
    return context.evaluated_depsgraph_get().scene


def list_item(context, index=-1):
    """The camera list item ``index`` (the active one when -1), or None."""
    settings = settings_of(context)
    i = settings.active_index if index < 0 else index
    return settings.cameras[i] if 0 <= i < len(settings.cameras) else None
