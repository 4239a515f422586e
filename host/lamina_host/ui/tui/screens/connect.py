"""Connect: find serial ports, connect, and show what the device reports about itself."""

from __future__ import annotations

from typing import ClassVar

from textual import on
from textual.app import ComposeResult
from textual.binding import Binding, BindingType
from textual.containers import Horizontal, Vertical
from textual.widgets import Button, Input, Label, OptionList, Static

from lamina_host.ui.tui.adapter import serial_ports
from lamina_host.ui.tui.widgets import LaminaScreen
from lamina_shared.messages import Welcome


def describe(info: Welcome | None) -> str:
    """Return the device information as lines of text."""
    if info is None:
        return "not connected"
    board = info.board
    board_text = (
        f"{board.inner_corners[0]}x{board.inner_corners[1]} corners, {board.square_mm:g} mm squares"
        if board
        else "not configured"
    )
    cylinder = f"{info.cylinder_diameter_mm:g} mm" if info.cylinder_diameter_mm else "unknown"
    return "\n".join(
        [
            f"protocol     {info.protocol}",
            f"software     {info.software}",
            f"hardware     {info.hardware}",
            f"description  {info.description}",
            f"camera       {info.image_size[0]} x {info.image_size[1]} px",
            f"board        {board_text}",
            f"cylinder     {cylinder}",
        ]
    )


class ConnectScreen(LaminaScreen):
    """Choose the device and connect to it."""

    MODE = "connect"
    AUTO_FOCUS = "#ports"
    BINDINGS: ClassVar[list[BindingType]] = [
        Binding("c", "connect", "Connect"),
        Binding("d", "disconnect", "Disconnect"),
        Binding("l", "list_ports", "List ports"),
    ]

    def body(self) -> ComposeResult:
        """Device field, port list and the device information."""
        with Horizontal(classes="row"):
            yield Label("Device", classes="field-label")
            yield Input(placeholder="sim, replay:DIR or /dev/ttyACM0", id="device", compact=True)
            yield Button("Connect", id="connect-button", compact=True)
        with Horizontal():
            with Vertical(id="ports-box", classes="panel"):
                yield Label("Ports (Enter picks)", classes="panel-title")
                yield OptionList(id="ports")
            with Vertical(classes="panel"):
                yield Label("Device information", classes="panel-title")
                yield Static("not connected", id="device-info")

    def on_mount(self) -> None:
        """Fill in the device and the port list."""
        self.query_one("#device", Input).value = self.job.device.name
        self.action_list_ports()

    def action_list_ports(self) -> None:
        """List the serial ports and the simulated device."""
        ports = self.query_one("#ports", OptionList)
        ports.clear_options()
        ports.add_options(["sim", *serial_ports()])

    @on(OptionList.OptionSelected, "#ports")
    def _pick(self, event: OptionList.OptionSelected) -> None:
        self.query_one("#device", Input).value = str(event.option.prompt)
        self.action_connect()

    @on(Input.Submitted, "#device")
    @on(Button.Pressed, "#connect-button")
    def _submit(self) -> None:
        self.action_connect()

    def action_connect(self) -> None:
        """Connect to the device named in the field."""
        device = self.query_one("#device", Input).value.strip()
        self.say(f"connecting to {device} ...")
        self.query_one("#device-info", Static).update("connecting ...")
        # In a thread: the handshake and the device's start-up take seconds.
        self.in_thread("connect", lambda: self.job.connect(device), self.connected)

    def connected(self, info: Welcome) -> None:
        """Show the device that answered."""
        self.refresh_from_job()
        self.say(f"connected to {self.job.device.name}: {info.software}, protocol {info.protocol}")

    def failed(self, message: str) -> None:
        """Show why connecting failed."""
        self.refresh_from_job()
        super().failed(message)

    def action_disconnect(self) -> None:
        """Close the link (in a thread: it waits for the device program to stop)."""
        self.in_thread("connect", self.job.close, lambda _: self.disconnected())

    def disconnected(self) -> None:
        """Show that no device is connected."""
        self.refresh_from_job()
        self.say("disconnected")

    def refresh_from_job(self) -> None:
        """Show the current device information."""
        self.query_one("#device-info", Static).update(describe(self.job.device.info))
