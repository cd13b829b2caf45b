"""Export panel: a mesh or points of the scene or the selection, the edited dataset, a camera path recorded from key
views and a video along it (the turntable without one). Exports run on the worker with a progress bar and Cancel;
the message line names where each file went."""
from __future__ import annotations

from imgui_bundle import imgui

from repaint_nerf.app.panels.common import remember_item, unavailable


def _browse(app, attr: str, folder: bool = False) -> None:
    """A '...' button opening the system file dialog (portable_file_dialogs); the typed path stays the fallback
    where no dialog program exists (e.g. under Xvfb)."""
    imgui.same_line()
    browse = imgui.button(f"...##{attr}")
    imgui.set_item_tooltip("choose the file in a dialog")
    if browse:
        try:
            from imgui_bundle import portable_file_dialogs as pfd

            current = getattr(app.state, attr)
            dlg = pfd.select_folder("Export folder", current) if folder else pfd.save_file("Export to", current)
            app.cache["file_dialog"] = (attr, dlg)
        except Exception as exc:  # no dialog backend: the text field still works
            app.state.say(f"no file dialog here ({exc}); type the path")
    pending = app.cache.get("file_dialog")
    if pending and pending[0] == attr and pending[1].ready():
        app.cache.pop("file_dialog")
        chosen = pending[1].result()
        if chosen:
            setattr(app.state, attr, chosen)


def _path(app, label: str, attr: str, tip: str, folder: bool = False) -> None:
    _, value = imgui.input_text(f"{label}##{attr}", getattr(app.state, attr))
    setattr(app.state, attr, value)
    remember_item(app, attr)
    imgui.set_item_tooltip(tip)
    _browse(app, attr, folder)


def _button(app, label: str, name: str, tip: str) -> bool:
    pressed = imgui.button(label)
    remember_item(app, name)
    imgui.set_item_tooltip(tip)
    return pressed


def draw(app) -> None:
    s = app.state
    opened = imgui.collapsing_header("Export")
    remember_item(app, "export_section")
    imgui.set_item_tooltip("a mesh, points, the edited dataset or a video of the current version")
    if not opened or unavailable(app, "render"):
        return
    job = s.export_job
    if job is not None:
        imgui.progress_bar(job.fraction, imgui.ImVec2(-1, 0), f"{job.kind}: {job.text}")
        if _button(app, "Cancel export", "export_cancel", "stop the export; nothing is written"):
            job.cancel = True
        imgui.text_wrapped(f"-> {job.target}")
        return
    _, s.export_selection = imgui.checkbox("Selection only", s.export_selection)
    remember_item(app, "export_selection")
    imgui.set_item_tooltip("export only the selected object (a mesh or points of it)")
    _, s.mesh_resolution = imgui.slider_int("Resolution##mesh", s.mesh_resolution, 64, 512)
    remember_item(app, "mesh_resolution")
    imgui.set_item_tooltip("voxels along the longest side for marching cubes: finer is slower and larger")
    _path(app, "Mesh", "mesh_path", "the mesh file: .glb, .ply or .obj (in world units)")
    if _button(app, "Export mesh", "export_mesh", "write the scene (or the selection) as a coloured mesh"):
        app.start_export(app.engine.export_mesh, s.mesh_path, selection=s.export_selection,
                         resolution=int(s.mesh_resolution))
    imgui.same_line()
    if _button(app, "Export points", "export_points", "write a coloured point cloud (.ply) of the surface"):
        app.start_export(app.engine.export_points, s.points_path, selection=s.export_selection)
    _path(app, "Points", "points_path", "the point cloud file (.ply)")
    _path(app, "Dataset", "dataset_path", "the folder Export dataset writes", folder=True)
    if _button(app, "Export dataset", "export_dataset",
               "the current version's renders as a nerfstudio / instant-ngp dataset, with selection masks"):
        app.start_export(app.engine.export_dataset, s.dataset_path)
    imgui.separator()
    imgui.text(f"Camera path: {len(s.path_keys)} key views")
    if _button(app, "Add key view", "path_add", "record the current view as the next key of the camera path"):
        app.add_path_key()
    imgui.same_line()
    if _button(app, "Clear keys", "path_clear", "forget the recorded key views"):
        s.path_keys.clear()
    _, s.path_frames = imgui.slider_int("Frames##path", s.path_frames, 8, 600)
    imgui.set_item_tooltip("frames of the video along the path (or of the turntable)")
    _, s.video_height = imgui.slider_int("Height##video", s.video_height, 64, 2160)
    imgui.set_item_tooltip("video height in pixels; the width follows the view's aspect")
    _path(app, "Path file", "camera_path_file", "where Save path writes the camera path (nerfstudio's JSON)")
    if _button(app, "Save path", "path_save", "save the key views as a nerfstudio camera_path.json"):
        app.save_camera_path(s.camera_path_file)
    _path(app, "Video", "export_video_path", "the video file (.mp4, or .gif)")
    label = "Video along path" if len(s.path_keys) >= 2 else "Turntable video"
    if _button(app, label, "export_video", "render the video: along the camera path with two or more key "
                                           "views, else once around the scene"):
        app.export_video(s.export_video_path)
