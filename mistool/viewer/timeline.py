"""The timeline: frame slider, play/pause, speed, step, loop, frame number and time, and
keyboard shortcuts.

One timeline is shared by every connected browser (a teacher scrubs, the class follows;
each browser keeps its own camera). All frame changes go through one render thread that
always draws the *latest* requested frame, so rapid scrubbing never queues a backlog and
never leaves a stale frame on screen. Keyboard shortcuts are viser commands (hotkeys):
space or K plays/pauses, J / L step one frame back / forward, Home goes to the first frame.
"""

from __future__ import annotations

import collections
import threading
import time
from collections.abc import Callable

import viser

#: Playback speeds offered (multiples of the sequence's fps).
SPEEDS = ("0.25x", "0.5x", "1x", "2x", "4x")


class Timeline:
    """Playback state and its GUI; calls ``draw(frame)`` from its own thread (started by
    :meth:`start`)."""

    def __init__(
        self, server: viser.ViserServer, num_frames: int, fps: float, draw: Callable[[int], object]
    ) -> None:
        """
        Args:
            server: the viser server (GUI shared by all clients).
            num_frames: frames in the sequence (>= 1).
            fps: the sequence's frames per second.
            draw: shows one frame (called from the render thread only).
        """
        self.server = server
        self.num_frames = int(num_frames)
        self.fps = float(fps)
        self._draw = draw
        self.growing = False
        """More frames are coming (tracking runs): playback holds at the last frame
        instead of looping or stopping."""
        self.follow = False
        """Show each new frame as it arrives (live use), until the user scrubs."""
        self._lock = threading.Lock()
        self._tick = threading.RLock()  # held while playback advances one frame
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._target = 0
        self._shown = -1
        self._dirty = False
        self.playing = False
        self.frames_drawn = 0
        self.draw_errors: collections.deque[BaseException] = collections.deque(maxlen=20)
        """The latest errors raised while drawing a frame (the replay keeps going)."""
        self.draw_error_count = 0
        gui = server.gui
        last = max(self.num_frames - 1, 1)
        self.slider = gui.add_slider(
            "Frame", min=0, max=last, step=1, initial_value=0, disabled=self.num_frames < 2
        )
        self.play_button = gui.add_button(
            "Play", icon=viser.Icon.PLAYER_PLAY, hint="Play / pause (space or K)"
        )
        self.step_buttons = gui.add_button_group("Step", ("-1 (J)", "+1 (L)"))
        self.speed = gui.add_dropdown("Speed", SPEEDS, initial_value="1x")
        self.loop = gui.add_checkbox("Loop", initial_value=True)
        self.info = gui.add_markdown(self._info_text(0))
        self.slider.on_update(self._slider_moved)
        self.play_button.on_click(lambda _: self.toggle())
        self.step_buttons.on_click(
            lambda e: self.step(-1 if str(e.target.value).startswith("-") else 1)
        )
        self.commands = [
            gui.add_command("Play / pause", hotkey="space", description="Toggle playback"),
            gui.add_command("Play / pause (K)", hotkey="K", description="Toggle playback"),
            gui.add_command("Previous frame", hotkey="J", description="Step back one frame"),
            gui.add_command("Next frame", hotkey="L", description="Step forward one frame"),
            gui.add_command("First frame", hotkey="home", description="Go to frame 0"),
        ]
        self.commands[0].on_trigger(lambda _: self.toggle())
        self.commands[1].on_trigger(lambda _: self.toggle())
        self.commands[2].on_trigger(lambda _: self.step(-1))
        self.commands[3].on_trigger(lambda _: self.step(1))
        self.commands[4].on_trigger(lambda _: self.seek(0))
        self._thread = threading.Thread(target=self._run, name="mistool-timeline", daemon=True)

    def _slider_moved(self, event: viser.GuiEvent) -> None:
        if event.client is not None and self.follow:
            latest = int(self.slider.value) >= self.num_frames - 1
            self.follow = latest  # scrubbing back stops following the newest frame
        self.request(int(self.slider.value))

    def set_num_frames(self, num_frames: int) -> None:
        """Frames available on the timeline (grows while a sequence is tracked); the
        slider's range follows, and with :attr:`follow` the newest frame is shown."""
        num_frames = max(1, int(num_frames))
        if num_frames == self.num_frames:
            return
        self.num_frames = num_frames
        self.slider.max = max(num_frames - 1, 1)
        self.slider.disabled = num_frames < 2
        if self.follow:
            self.seek(num_frames - 1)
        self._wake.set()

    def start(self) -> None:
        """Start the render thread (once everything ``draw`` uses exists)."""
        self._thread.start()

    # -- control ------------------------------------------------------------------------
    @property
    def frame(self) -> int:
        """The frame most recently requested."""
        return self._target

    @property
    def shown(self) -> int:
        """The frame most recently drawn (-1 before the first)."""
        return self._shown

    def speed_factor(self) -> float:
        """The selected speed as a multiple of the sequence's fps."""
        return float(str(self.speed.value).rstrip("x"))

    def request(self, frame: int) -> None:
        """Ask for ``frame`` to be shown (clamped); returns at once."""
        frame = min(max(int(frame), 0), self.num_frames - 1)
        with self._lock:
            self._target = frame
        self._wake.set()

    def redraw(self) -> None:
        """Draw the current frame again (display options changed)."""
        self._dirty = True
        self._wake.set()

    def seek(self, frame: int) -> None:
        """Move the slider (and so every browser) to ``frame``."""
        frame = min(max(int(frame), 0), self.num_frames - 1)
        # viser 1.1.1 defines the value setter apart from its getter: mypy reads it as read-only
        self.slider.value = frame  # type: ignore[misc]
        self.request(frame)

    def step(self, delta: int) -> None:
        """Pause and move ``delta`` frames (wrapping when looping)."""
        self.set_playing(False)
        frame = self._target + delta
        if self.loop.value:
            frame %= self.num_frames
        self.seek(frame)

    def toggle(self) -> None:
        """Play if paused, pause if playing."""
        self.set_playing(not self.playing)

    def set_playing(self, playing: bool) -> None:
        """Start or stop playback. Once it returns after stopping, no further frame
        advance happens (a step in progress has finished)."""
        with self._tick:
            if playing == self.playing:
                return
            at_end = self._target >= self.num_frames - 1
            if playing and at_end and not self.loop.value and not self.growing:
                self.seek(0)
            self.playing = playing
            self.play_button.label = "Pause" if playing else "Play"
            self.play_button.icon = viser.Icon.PLAYER_PAUSE if playing else viser.Icon.PLAYER_PLAY
        self._wake.set()

    def stop(self) -> None:
        """Stop the render thread (the GUI stays)."""
        self._stop.set()
        self._wake.set()
        if self._thread.is_alive():
            self._thread.join(timeout=5.0)

    def wait_shown(self, frame: int, timeout: float = 5.0) -> bool:
        """Block until ``frame`` has been drawn (tests and benchmarks)."""
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if self._shown == frame:
                return True
            time.sleep(0.002)
        return False

    # -- render thread ------------------------------------------------------------------
    def _info_text(self, frame: int) -> str:
        return f"**Frame** {frame} / {self.num_frames - 1} &nbsp; **Time** {frame / self.fps:.2f} s"

    def _run(self) -> None:
        next_tick = time.monotonic()
        while not self._stop.is_set():
            if self.playing:
                period = 1.0 / (self.fps * self.speed_factor())
                now = time.monotonic()
                if now < next_tick:
                    self._wake.wait(next_tick - now)
                    self._wake.clear()
                    if not self.playing or self._stop.is_set():
                        continue
                    if time.monotonic() < next_tick:  # woken by a scrub: draw it now
                        self._draw_target()
                        continue
                # Hold the frame rate: schedule from the previous tick (a late frame is
                # made up by the next ones), but after a stall of more than three periods
                # start afresh instead of rushing through frames.
                next_tick += period
                if time.monotonic() - next_tick > 3 * period:
                    next_tick = time.monotonic()
                with self._tick:  # set_playing(False) waits for this step to finish
                    if not self.playing:
                        continue
                    frame = self._target + 1
                    if frame >= self.num_frames:
                        if self.growing:  # hold at the newest frame until more come
                            continue
                        if self.loop.value:
                            frame = 0
                        else:
                            self.set_playing(False)
                            continue
                    with self._lock:
                        self._target = frame
                    self.slider.value = frame  # type: ignore[misc]  # (see seek)
                    self._draw_target()
            else:
                self._wake.wait(0.5)
                self._wake.clear()
                next_tick = time.monotonic()
                self._draw_target()

    def _draw_target(self) -> None:
        frame = self._target
        if frame == self._shown and not self._dirty:
            return
        self._dirty = False  # a redraw asked for while drawing draws again
        try:
            self._draw(frame)
            self.info.content = self._info_text(frame)
        except Exception as exc:  # keep the replay alive; `mistool serve` reports them
            self.draw_errors.append(exc)
            self.draw_error_count += 1
        self._shown = frame
        self.frames_drawn += 1
