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
        self._blit: tuple | None = None  # the blit program and its vertex array, made on first use
        self._window_cache = _WindowCache(self.ctx)
        # Windows are opaque: a panel covers what is under it (end_frame's `cached` window is blitted opaque)
        bg = imgui.get_style().color_(imgui.Col_.window_bg)
        imgui.get_style().set_color_(imgui.Col_.window_bg, imgui.ImVec4(bg.x, bg.y, bg.z, 1.0))

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

    def end_frame(self, capture: bool = False, present: bool = True, bare: list | None = None,
                  underlay: tuple | None = None, cached: tuple | None = None) -> np.ndarray | None:
        """Draw imgui and present; with `capture`, return the finished frame as uint8 RGB (H, W, 3). With
        `present` false the frame ends without drawing (and without a capture): the screen keeps the last
        picture. On a software rasterizer every pixel drawn costs, so:
        - `underlay` (texture, rect) is a picture blitted opaque under imgui's windows (the viewport's), its rows
          stored top first;
        - `bare` lists the rects that neither it nor a window covers, the only ones cleared (None: the screen);
        - `cached` (draw list, rect) is an opaque window redrawn only when its draw list changed (the panels:
          4.5 of a UI frame's 10 ms on llvmpipe), else blitted from the last time it was drawn.
        Rects are (x, y, w, h) in window coordinates."""
        imgui.render()
        if not present:
            return None
        w, h = self.framebuffer_size()
        draw_data = imgui.get_draw_data()
        lists = [draw_data.cmd_lists[i] for i in range(draw_data.cmd_lists_count)]
        at = next((i for i, dl in enumerate(lists) if cached is not None and dl is cached[0]), None)
        if at is not None:
            self._window_cache.update(lists[at], self.fb_rect(cached[1]), draw_data, (w, h))
        self.ctx.screen.use()
        if bare is None:
            self.ctx.viewport = (0, 0, w, h)
            self.ctx.clear(0.1, 0.1, 0.12, 1.0)
        for rect in bare or ():
            fb = self.fb_rect(rect)
            if fb[2] > 0 and fb[3] > 0:
                self.ctx.clear(0.1, 0.1, 0.12, 1.0, viewport=fb)
        if underlay is not None:
            self.blit(underlay[0], self.fb_rect(underlay[1]), src=(0.0, 1.0, 1.0, -1.0))
        if at is None:
            self.ctx.viewport = (0, 0, w, h)
            imgui.backends.opengl3_render_draw_data(draw_data)
        else:
            _render_lists(draw_data, lists[:at], textures=True)
            self._window_cache.blit(self)
            _render_lists(draw_data, lists[at + 1:])
        shot = self._read_screen(w, h) if capture else None
        glfw.swap_buffers(self.handle)
        return shot

    def blit(self, texture: moderngl.Texture, rect: tuple[int, int, int, int],
             src: tuple[float, float, float, float] = (0.0, 0.0, 1.0, 1.0)) -> None:
        """Draw `texture`'s region `src` (u, v at the rect's bottom-left, then the step to its top-right) over the
        bound framebuffer's pixel `rect` (GL's bottom-left origin), opaque. A region of one texel a pixel is read
        with the nearest filter, the same picture for less than a bilinear read costs."""
        if self._blit is None:
            from repaint_nerf.app.viewport import load_shader

            prog = self.ctx.program(vertex_shader=load_shader("viewport.vert"),
                                    fragment_shader=load_shader("blit.frag"))
            self._blit = (prog, self.ctx.vertex_array(prog, []))
        prog, vao = self._blit
        one_to_one = (abs(abs(src[2]) * texture.width - rect[2]) < 0.5
                      and abs(abs(src[3]) * texture.height - rect[3]) < 0.5)
        filt = moderngl.NEAREST if one_to_one else moderngl.LINEAR
        texture.filter = (filt, filt)
        texture.repeat_x = texture.repeat_y = False  # a bilinear read at the edge must not wrap to the other side
        texture.use(location=0)
        prog["picture"] = 0
        prog["src_origin"] = src[:2]
        prog["src_size"] = src[2:]
        self.ctx.viewport = rect
        self.ctx.disable(moderngl.BLEND | moderngl.DEPTH_TEST)
        vao.render(moderngl.TRIANGLES, vertices=3)

    def fb_rect(self, rect: tuple[float, float, float, float]) -> tuple[int, int, int, int]:
        """A rect in window coordinates (x, y, w, h; top-left origin, as imgui's) in framebuffer pixels with GL's
        bottom-left origin (a HiDPI screen's framebuffer has more pixels than the window has units)."""
        sx, sy = imgui.get_io().display_framebuffer_scale
        fb_h = self.framebuffer_size()[1]
        x, y, w, h = rect
        x0, x1 = round(x * sx), round((x + w) * sx)
        y0, y1 = round(y * sy), round((y + h) * sy)
        return x0, fb_h - y1, x1 - x0, y1 - y0

    def _read_screen(self, w: int, h: int) -> np.ndarray:
        data = self.ctx.screen.read(viewport=(0, 0, w, h), components=3, alignment=1)
        return np.frombuffer(data, dtype=np.uint8).reshape(h, w, 3)[::-1].copy()

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._window_cache.release()
        imgui.backends.opengl3_shutdown()
        imgui.backends.glfw_shutdown()
        implot.destroy_context()
        imgui.destroy_context()
        glfw.destroy_window(self.handle)
        glfw.terminate()


_DRAW_VERT_BYTES = 20  # ImDrawVert: position (2 floats), texture coordinate (2 floats), colour (4 bytes)


class _WindowCache:
    """One imgui window's pixels, kept in a framebuffer-sized texture and redrawn only when its draw list (vertices,
    indices, commands) or its place changed: a panel whose text did not change is not rasterized again, and one
    whose text changed in a few places is rasterized again only there (`_damage`): on llvmpipe the whole panel
    costs 8-9 ms, the most of a UI frame, where a status line's digits changed."""

    def __init__(self, ctx: moderngl.Context):
        self.ctx = ctx
        self.texture: moderngl.Texture | None = None
        self.fbo: moderngl.Framebuffer | None = None
        self.rect: tuple[int, int, int, int] | None = None
        self.signature: tuple | None = None
        self.triangles: np.ndarray | None = None  # the last drawn list's `_triangles`
        self.redraws = 0  # times the window was rasterized, in full or in part (the rest were blits)
        self.partial_redraws = 0  # of those, the ones limited to the changed rects
        self.damaged = 0.0  # share of the window's pixels the last redraw rasterized

    def update(self, draw_list, rect: tuple[int, int, int, int], draw_data, size: tuple[int, int]) -> None:
        """Redraw the window into the texture when `draw_list` or `rect` (framebuffer pixels) changed: only
        the rects its changed triangles cover when the texture holds this window at this place."""
        content = _draw_list_bytes(draw_list)
        signature = (rect, size, content)
        if signature == self.signature and self.texture is not None:
            return
        triangles = _triangles(*content, _index_dtype(draw_list))
        damage = None
        if self.texture is not None and self.texture.size == size and self.rect == rect:
            damage = _damage(self.triangles, triangles, draw_data, size[1], rect)
        if self.texture is None or self.texture.size != size:
            if self.fbo is not None:
                self.fbo.release()
                self.texture.release()
            self.texture = self.ctx.texture(size, 4)
            self.fbo = self.ctx.framebuffer(color_attachments=[self.texture])
        self.fbo.use()
        if damage is None:
            self.ctx.clear(0.0, 0.0, 0.0, 0.0, viewport=rect)
            _render_lists(draw_data, [draw_list], textures=True)
            self.damaged = 1.0
        else:
            _render_lists(draw_data, [], textures=True)  # new glyphs reach the GPU before a triangle reads them
            for fb_rect, clip in damage:
                self.ctx.clear(0.0, 0.0, 0.0, 0.0, viewport=fb_rect)
                _render_clipped(draw_data, draw_list, clip)
            self.damaged = sum(r[2] * r[3] for r, _ in damage) / float(max(rect[2] * rect[3], 1))
            self.partial_redraws += 1
        self.rect, self.signature, self.triangles = rect, signature, triangles
        self.redraws += 1

    def blit(self, window: "Window") -> None:
        if self.texture is None or self.rect is None:
            return
        x, y, w, h = self.rect
        tw, th = self.texture.size
        window.blit(self.texture, self.rect, src=(x / tw, y / th, w / tw, h / th))

    def release(self) -> None:
        if self.fbo is not None:
            self.fbo.release()
            self.texture.release()
        self.fbo = self.texture = self.signature = self.triangles = None


def _draw_list_bytes(draw_list) -> tuple:
    """What a draw list draws, as bytes to compare: its vertices and indices, and each command's clip rect,
    texture and element range."""
    import ctypes

    vtx, idx = draw_list.vtx_buffer, draw_list.idx_buffer
    cmds = tuple(((c.clip_rect.x, c.clip_rect.y, c.clip_rect.z, c.clip_rect.w), c.tex_ref._tex_id, c.elem_count,
                  c.idx_offset, c.vtx_offset)  # the texture by id: one the backend has not made yet has none
                 for c in (draw_list.cmd_buffer[i] for i in range(draw_list.cmd_buffer.size())))
    return (ctypes.string_at(vtx.data_address(), vtx.size() * _DRAW_VERT_BYTES),
            ctypes.string_at(idx.data_address(), idx.size() * np.dtype(_index_dtype(draw_list)).itemsize), cmds)


def _index_dtype(draw_list) -> type:
    """ImDrawIdx as imgui_bundle compiles it: 32-bit where the index vector is an ImVector_uint, else 16-bit."""
    return np.uint32 if type(draw_list.idx_buffer).__name__ == "ImVector_uint" else np.uint16


MAX_DAMAGE_RECTS = 4  # more separate changes than this redraw the window's bounding rect of them all
_TRI_WORDS = 3 * _DRAW_VERT_BYTES // 4 + 5  # a triangle's three vertices, then its command's clip rect and texture


def _triangles(vtx: bytes, idx: bytes, cmds: tuple, index_dtype: type) -> np.ndarray | None:
    """Every triangle a draw list draws (`_draw_list_bytes`; its indices of `index_dtype`), in draw order, as a
    row of uint32 words (`_TRI_WORDS`): its three vertices' bytes (position first), then its command's clip rect
    and texture. Rows compare equal exactly where the triangle draws the same pixels, wherever it sits in the
    buffers. None for a list that is not plain triangles (a command with no whole triangles)."""
    verts = np.frombuffer(vtx, np.uint32).reshape(-1, _DRAW_VERT_BYTES // 4)
    index = np.frombuffer(idx, index_dtype)
    rows = []
    for clip, tex, count, offset, vtx_offset in cmds:
        if count % 3:
            return None
        if not count:
            continue
        corners = index[offset:offset + count].astype(np.int64) + vtx_offset
        tri = verts[corners].reshape(-1, 3 * _DRAW_VERT_BYTES // 4)
        key = np.concatenate([np.array(clip, np.float32).view(np.uint32), [np.uint32(int(tex or 0) & 0xFFFFFFFF)]])
        rows.append(np.concatenate([tri, np.broadcast_to(key, (len(tri), 5))], 1))
    return np.concatenate(rows) if rows else np.zeros((0, _TRI_WORDS), np.uint32)


def _changed(old: np.ndarray, new: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(old rows, new rows) that differ between two triangle lists: after their common first and last rows; where
    the two middles have one length, only the rows that differ there (a number whose digits changed, in place)."""
    n = min(len(old), len(new))
    differ = np.any(old[:n] != new[:n], 1)
    first = int(np.argmax(differ)) if differ.any() else n
    tail = np.any(old[len(old) - n + first:][::-1] != new[len(new) - n + first:][::-1], 1)
    last = int(np.argmax(tail)) if tail.any() else n - first
    a, b = old[first:len(old) - last], new[first:len(new) - last]
    if len(a) == len(b):
        rows = np.any(a != b, 1)
        a, b = a[rows], b[rows]
    return a, b


def _damage(old: np.ndarray | None, new: np.ndarray | None, draw_data, fb_height: int,
            rect: tuple[int, int, int, int]) -> list | None:
    """The rects to redraw when a window's triangles went from `old` to `new`: [(framebuffer rect (GL origin),
    clip rect in imgui coordinates)], the changed triangles' bounds grouped into at most MAX_DAMAGE_RECTS bands
    down the window; None where only a full redraw is safe: no old triangles, a clip rect off the pixel grid (the
    backend truncates its scissor, so an intersection could move an edge a pixel), or changes over most of it."""
    if old is None or new is None:
        return None
    a, b = _changed(old, new)
    rows = np.concatenate([a, b])
    if not len(rows):
        return []
    sx, sy = (float(v) for v in (draw_data.framebuffer_scale.x, draw_data.framebuffer_scale.y))
    ox, oy = float(draw_data.display_pos.x), float(draw_data.display_pos.y)
    clips = np.concatenate([old[:, -5:-1], new[:, -5:-1]]).view(np.float32)
    scaled = (clips - [ox, oy, ox, oy]) * [sx, sy, sx, sy]
    if not np.all(np.isfinite(scaled)) or np.any(scaled != np.round(scaled)):
        return None
    pos = rows[:, :15].reshape(-1, 3, 5)[:, :, :2].copy().view(np.float32).reshape(-1, 3, 2)
    lo = np.floor((pos.min(1) - [ox, oy]) * [sx, sy]) - 1  # a pixel's margin for the antialiased fringe
    hi = np.ceil((pos.max(1) - [ox, oy]) * [sx, sy]) + 1
    order = np.argsort(lo[:, 1], kind="stable")  # triangles by their top: a band ends where the next one starts
    lo, hi = lo[order], hi[order]  # below every triangle before it (a plot's thousands of triangles: no loop)
    bottom = np.maximum.accumulate(hi[:, 1])
    starts = np.concatenate([[0], np.nonzero(lo[1:, 1] > bottom[:-1])[0] + 1])
    if len(starts) > MAX_DAMAGE_RECTS:
        starts = starts[:1]
    bands = np.stack([np.minimum.reduceat(lo[:, 0], starts), lo[starts, 1], np.maximum.reduceat(hi[:, 0], starts),
                      np.maximum.reduceat(hi[:, 1], starts)], 1).tolist()
    x0, y0, w, h = rect  # the window in framebuffer pixels, GL origin
    top = fb_height - (y0 + h)  # its top row from the top
    out, area = [], 0
    for bx0, by0, bx1, by1 in bands:
        bx0, bx1 = max(bx0, x0), min(bx1, x0 + w)
        by0, by1 = max(by0, top), min(by1, top + h)
        if bx1 <= bx0 or by1 <= by0:
            continue
        fb = (int(bx0), int(fb_height - by1), int(bx1 - bx0), int(by1 - by0))
        clip = (bx0 / sx + ox, by0 / sy + oy, bx1 / sx + ox, by1 / sy + oy)
        out.append((fb, clip))
        area += fb[2] * fb[3]
    if area > 0.6 * w * h:
        return None
    return out


def _render_clipped(draw_data, draw_list, clip: tuple[float, float, float, float]) -> None:
    """Render `draw_list` with every command's clip rect cut to `clip` (imgui coordinates): only the pixels inside
    change, each as the full draw makes it (the same vertices, the same projection)."""
    cmds = [draw_list.cmd_buffer[i] for i in range(draw_list.cmd_buffer.size())]
    saved = [(c.clip_rect.x, c.clip_rect.y, c.clip_rect.z, c.clip_rect.w) for c in cmds]
    try:
        for c, (x0, y0, x1, y1) in zip(cmds, saved):
            c.clip_rect = imgui.ImVec4(max(x0, clip[0]), max(y0, clip[1]), min(x1, clip[2]), min(y1, clip[3]))
        _render_lists(draw_data, [draw_list])
    finally:
        for c, r in zip(cmds, saved):
            c.clip_rect = imgui.ImVec4(*r)


def _render_lists(draw_data, lists: list, textures: bool = False) -> None:
    """Render some of a frame's draw lists, in order, with imgui's OpenGL backend into the bound framebuffer
    (`textures`: this call also makes the frame's texture updates, e.g. new font glyphs, with no lists as well: a
    cached panel first in the draw order left nothing before it to carry them)."""
    if not lists and not textures:
        return
    part = imgui.ImDrawData()
    part.display_pos, part.display_size = draw_data.display_pos, draw_data.display_size
    part.framebuffer_scale = draw_data.framebuffer_scale
    if textures:
        part.textures = draw_data.textures
    for dl in lists:
        part.add_draw_list(dl)
    imgui.backends.opengl3_render_draw_data(part)


def _window_address(handle) -> int:
    import ctypes

    return ctypes.cast(handle, ctypes.c_void_p).value
