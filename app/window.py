"""The editor's OS window: glfw + a moderngl context + imgui-bundle's glfw/OpenGL3 backends.

One `Window` per process. Each frame: `begin_frame()`, imgui widgets, `end_frame()`. Tests and the
viewport benchmark inject imgui input events through `inject(...)`; they are queued after the glfw
backend has read the real devices and before `imgui.new_frame()`, so they win over the real cursor.
"""
from __future__ import annotations

import os
from typing import Callable

import imgui_bundle  # noqa: F401  (must come before glfw: it points pyGLFW at its bundled libglfw)
from imgui_bundle import imgui, implot
import glfw  # noqa: E402
import moderngl  # noqa: E402
import numpy as np  # noqa: E402

from repaint_nerf.core.errors import UserError  # noqa: E402


def mouse_event(x: float, y: float, button: int | None = None, down: bool | None = None, shift: bool = False,
                ctrl: bool = False) -> Callable[["imgui.IO"], None]:
    """An injector (for `Window.inject`) that moves the mouse to (x, y) and optionally presses or releases
    `button`, with the shift / ctrl modifiers held: scripted input for GUI tests and the viewport benchmark."""

    def fn(io: "imgui.IO") -> None:
        if shift or ctrl:  # key events before a button event would delay it a frame (imgui's input trickling)
            io.add_key_event(imgui.Key.mod_shift, shift)
            io.add_key_event(imgui.Key.mod_ctrl, ctrl)
        io.add_mouse_pos_event(x, y)
        if button is not None:
            io.add_mouse_button_event(button, bool(down))
    fn.button = button is not None  # a click ends the UI's pacing wait, as a real one does (Window.clicked)
    return fn


class _GlfwLoader:
    """moderngl's loader interface over glfw.get_proc_address (the window's current context)."""

    def load_opengl_function(self, name: str) -> int:
        return glfw.get_proc_address(name) or 0

    def release(self) -> None:
        pass


class Window:
    """A glfw window with GL 3.3 core, moderngl and imgui (+ implot) set up."""

    def __init__(self, title: str = "RePaint-NeRF", width: int = 1280, height: int = 800, visible: bool = True):
        if not glfw.init():
            raise UserError("cannot open a window: no display was found",
                            hint="run under a desktop session, or set DISPLAY (e.g. start `Xvfb :99` and export DISPLAY=:99)")
        glfw.window_hint(glfw.CONTEXT_VERSION_MAJOR, 3)
        glfw.window_hint(glfw.CONTEXT_VERSION_MINOR, 3)
        glfw.window_hint(glfw.OPENGL_PROFILE, glfw.OPENGL_CORE_PROFILE)
        glfw.window_hint(glfw.OPENGL_FORWARD_COMPAT, True)
        glfw.window_hint(glfw.VISIBLE, visible)
        # The platform's API (GLX on X11) presents fast: with Mesa's llvmpipe under Xvfb an EGL window's
        # swap costs 13 ms per 1280x800 frame, a GLX window's 0.4 ms. But once a process holds an EGL context
        # (core's scene rasterizer), Mesa refuses GLX ones (BadAccess in glXMakeCurrent): then EGL.
        # $REPAINT_NERF_GL_API = egl | native overrides.
        from repaint_nerf.core.synth.raster import egl_context_made

        api = os.environ.get("REPAINT_NERF_GL_API", "auto")
        apis = [glfw.NATIVE_CONTEXT_API, glfw.EGL_CONTEXT_API]
        if api == "egl" or (api == "auto" and egl_context_made()):
            apis.reverse()
        self.handle = None
        for choice in apis:  # the other API when the display offers no context of the first
            glfw.window_hint(glfw.CONTEXT_CREATION_API, choice)
            self.handle = glfw.create_window(width, height, title, None, None)
            if self.handle:
                break
        if not self.handle:
            glfw.terminate()
            raise UserError("cannot create an OpenGL 3.3 window", hint="update the graphics driver (or Mesa)")
        glfw.make_context_current(self.handle)
        glfw.swap_interval(0 if os.environ.get("REPAINT_NERF_NO_VSYNC") else 1)
        # moderngl takes GL functions from glfw, whichever API (GLX or EGL) made the context: its own lookup
        # is GLX's, which misses an EGL context once an earlier window's context is moderngl's default.
        moderngl.init_context(_GlfwLoader())
        self.ctx = moderngl.get_context()
        imgui.create_context()
        implot.create_context()
        io = imgui.get_io()
        io.config_flags |= imgui.ConfigFlags_.nav_enable_keyboard.value
        io.set_ini_filename("")  # no imgui.ini next to the user's data
        self._clicked = False
        self._navigated = False
        self._held: set[int] = set()  # mouse buttons down, from glfw's callbacks
        # installed before imgui's backend, which chains them (one libglfw: imgui_bundle's)
        glfw.set_mouse_button_callback(self.handle, self._on_button)
        glfw.set_cursor_pos_callback(self.handle, self._on_cursor)
        glfw.set_scroll_callback(self.handle, self._on_scroll)
        imgui.backends.glfw_init_for_opengl(_window_address(self.handle), True)
        imgui.backends.opengl3_init("#version 330")
        self._injectors: list[Callable[[imgui.IO], None]] = []
        self._closed = False

    def inject(self, fn: Callable[["imgui.IO"], None]) -> None:
        """Queue a function that adds imgui input events for the next frame (tests, scripted benchmarks)."""
        self._injectors.append(fn)
        self._clicked = self._clicked or bool(getattr(fn, "button", False))

    def _on_button(self, handle, button: int, action: int, mods: int) -> None:
        self._clicked = True
        (self._held.add if action == glfw.PRESS else self._held.discard)(button)

    def _on_cursor(self, handle, x: float, y: float) -> None:
        self._navigated = self._navigated or bool(self._held)  # a drag moved; hovering is not navigation

    def _on_scroll(self, handle, dx: float, dy: float) -> None:
        self._navigated = True

    def clicked(self) -> bool:
        """A mouse button went down or up since this frame began: a patch's release or a press is answered
        at once, while mouse motion keeps the frame pace."""
        return self._clicked

    def navigated(self) -> bool:
        """The mouse moved with a button held, or the wheel turned, since this frame began: input that may
        move the camera (the editor answers the first such input after the view rests without a pacing wait)."""
        return self._navigated

    def should_close(self) -> bool:
        return self._closed or glfw.window_should_close(self.handle)

    def request_close(self) -> None:
        glfw.set_window_should_close(self.handle, True)

    def framebuffer_size(self) -> tuple[int, int]:
        return glfw.get_framebuffer_size(self.handle)

    def wait_events(self, timeout: float) -> None:
        """Sleep until an input event or `wake()`, at most `timeout` seconds (an idle UI costs no CPU)."""
        glfw.wait_events_timeout(timeout)

    def wake(self) -> None:
        """Wake a `wait_events` from another thread."""
        glfw.post_empty_event()

    def has_pending_input(self) -> bool:
        """Scripted input (tests) is queued for the next frames."""
        return bool(self._injectors)

    def begin_frame(self) -> None:
        self._clicked = self._navigated = False
        glfw.poll_events()
        imgui.backends.opengl3_new_frame()
        imgui.backends.glfw_new_frame()
        io = imgui.get_io()
        injectors, self._injectors = self._injectors, []
        for fn in injectors:
            fn(io)
        imgui.new_frame()

    def end_frame(self, capture: bool = False, present: bool = True, clear: bool = True) -> np.ndarray | None:
        """Draw imgui and present; with `capture`, return the finished frame as uint8 RGB (H, W, 3). With
        `present` false the frame ends without drawing (and without a capture): the screen keeps the last
        picture. `clear` false
        when opaque windows cover the whole screen (a full-screen pass less on a software rasterizer)."""
        imgui.render()
        if not present:
            return None
        w, h = self.framebuffer_size()
        self.ctx.screen.use()
        self.ctx.viewport = (0, 0, w, h)
        if clear:
            self.ctx.clear(0.1, 0.1, 0.12, 1.0)
        imgui.backends.opengl3_render_draw_data(imgui.get_draw_data())
        shot = self._read_screen(w, h) if capture else None
        glfw.swap_buffers(self.handle)
        return shot

    def _read_screen(self, w: int, h: int) -> np.ndarray:
        data = self.ctx.screen.read(viewport=(0, 0, w, h), components=3, alignment=1)
        return np.frombuffer(data, dtype=np.uint8).reshape(h, w, 3)[::-1].copy()

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        imgui.backends.opengl3_shutdown()
        imgui.backends.glfw_shutdown()
        implot.destroy_context()
        imgui.destroy_context()
        glfw.destroy_window(self.handle)
        glfw.terminate()


def _window_address(handle) -> int:
    import ctypes

    return ctypes.cast(handle, ctypes.c_void_p).value
