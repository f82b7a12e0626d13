"""Panels: Properties -> Render -> "Caustic Bake", and Properties -> Object -> "Caustic Bake".
Thin: they show settings and state; no maths here."""

import bpy

from .state import SHORT_MISSING_NUMBA, STATE, numba_missing


class _PropertiesPanel:
    """What every panel here shares: the Properties editor, closed until opened."""

    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_options = {"DEFAULT_CLOSED"}


def _settings_layout(layout):
    """``layout`` set out for settings: labels split from their fields, no animation dots."""
    layout.use_property_split = True
    layout.use_property_decorate = False
    return layout


class _ScenePanel(_PropertiesPanel):
    """A panel of the scene's Caustic Bake settings (Properties -> Render)."""

    bl_context = "render"

    @classmethod
    def poll(cls, context):
        return context.scene is not None and hasattr(context.scene, "caustic_bake")


class RENDER_PT_caustic_bake(_ScenePanel, bpy.types.Panel):
    bl_label = "Caustic Bake"
    bl_idname = "RENDER_PT_caustic_bake"

    def draw(self, context):
        from ..bake.extract import readiness
        from .operators import baked_images, output_directory

        layout = _settings_layout(self.layout)
        props = context.scene.caustic_bake

        missing = numba_missing()
        if missing:
            box = layout.box()
            box.alert = True
            box.label(text=SHORT_MISSING_NUMBA, icon="ERROR")
            box.label(text="({} could not be found)".format(missing))

        if STATE.running:
            col = layout.column()
            col.progress(factor=STATE.fraction, type="BAR", text="{:.0f}%  {}".format(100 * STATE.fraction, STATE.message))
            col.label(text="Baking... press Esc to cancel", icon="INFO")
        else:
            receivers, lights = readiness(context.scene)
            if not receivers:
                layout.label(text="No receivers: a mesh needs a UV map (or Receiver: Yes)", icon="INFO")
            if not lights:
                layout.label(text="No lights in the scene", icon="INFO")
            row = layout.row(align=True)
            row.scale_y = 1.5
            row.operator("caustics.bake", icon="RENDER_STILL")
            row.operator("caustics.clear", text="", icon="TRASH")

        images = baked_images()
        if images:
            box = layout.box()
            box.label(text="Baked: {} texture(s)".format(len(images)), icon="CHECKMARK")
            for name in images[:8]:
                box.label(text=name, icon="IMAGE_DATA")
            if len(images) > 8:
                box.label(text="... and {} more".format(len(images) - 8))
            for line in (props.last_plan or "").split("\n")[:8]:
                if line:
                    box.label(text=line, icon="LIGHT")

        col = layout.column()
        col.enabled = not STATE.running
        col.prop(props, "resolution")
        col.prop(props, "quality")
        sub = col.column()
        sub.active = props.quality == "FINAL"
        sub.prop(props, "samples")
        sub.prop(props, "light_samples")
        col.prop(props, "bounces")
        if props.bounces == "auto":
            col.prop(props, "plan_threshold")
        col.separator()
        col.prop(props, "estimator")
        if props.estimator == "path-points":
            col.prop(props, "solver")
            if props.solver == "sms":
                col.prop(props, "sms_seeds")
            col.prop(props, "device")
        elif props.estimator == "forward-flux":
            col.prop(props, "device")
        elif props.estimator == "photon":
            col.prop(props, "photons")
        col.prop(props, "seed")
        col.prop(props, "margin")
        col.prop(props, "memory_budget")
        col.separator()
        col.prop(props, "output_dir")
        col.prop(props, "pack")
        if output_directory(props) is None:  # relative to an unsaved .blend: packed
            col.label(text="Unsaved file: the textures will be packed", icon="PACKAGE")


class RENDER_PT_caustic_bake_animation(_ScenePanel, bpy.types.Panel):
    bl_label = "Animation"
    bl_idname = "RENDER_PT_caustic_bake_animation"
    bl_parent_id = "RENDER_PT_caustic_bake"

    def draw(self, context):
        from .operators import output_directory

        layout = _settings_layout(self.layout)
        props = context.scene.caustic_bake
        col = layout.column()
        col.enabled = not STATE.running
        col.prop(props, "frame_range")
        if props.frame_range == "SCENE":
            sc = context.scene
            n = max(0, sc.frame_end - sc.frame_start + 1)
            col.label(text="Frames {}-{}: {} EXR(s) per receiver".format(sc.frame_start, sc.frame_end, n), icon="SEQUENCE")
            if output_directory(props) is None:  # relative to an unsaved .blend: nowhere to write a sequence
                col.label(text="Save the .blend first: a sequence is written, not packed", icon="ERROR")


class OBJECT_PT_caustic_bake(_PropertiesPanel, bpy.types.Panel):
    bl_label = "Caustic Bake"
    bl_idname = "OBJECT_PT_caustic_bake"
    bl_context = "object"

    @classmethod
    def poll(cls, context):
        ob = context.object
        return ob is not None and ob.type == "MESH" and hasattr(ob, "caustic_bake")

    def draw(self, context):
        layout = _settings_layout(self.layout)
        ob = context.object
        props = ob.caustic_bake
        col = layout.column()
        col.enabled = not STATE.running
        col.prop(props, "role")
        col.prop(props, "receiver")
        sub = col.column()
        sub.active = props.receiver != "no"
        sub.prop(props, "resolution")
        if props.receiver != "no" and not ob.data.uv_layers:
            col.label(text="No UV map: cannot receive caustics", icon="ERROR" if props.receiver == "yes" else "INFO")


classes = (RENDER_PT_caustic_bake, RENDER_PT_caustic_bake_animation, OBJECT_PT_caustic_bake)
