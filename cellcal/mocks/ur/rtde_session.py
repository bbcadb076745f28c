"""One RTDE connection of the UR twin (TCP 30004): protocol version, recipes, the output
rate, start and pause. Stdlib only; the child's loop feeds it bytes and sends what it
returns.

What it answers (UR's RTDE guide; UR's and SDU's clients parse it so):

* ``V``: versions 1 and 2 are accepted (1), any other refused (0). v1 frames v1: no
  frequency in the output setup, no recipe id in the setup-outputs reply nor in the
  data packages, at most one output recipe (a new setup replaces it), text messages in
  v1 layout. v1 outputs go out at 500 Hz, the controller's rate.
* ``v``: 5.11.1.108318.
* ``O``: the types of the names in order, ``NOT_FOUND`` for unknown ones; recipe id 0
  (refused) if any is not found, else 1, 2, ... per connection. The v2 frequency must be
  finite and within (0, 500] Hz: an invalid one is refused with an error text message
  (``M``) and a setup-outputs reply with recipe id 0 and no types, which UR's client
  fails on and on which a start is refused. (The guide does not document the
  controller's answer to an invalid frequency; this is the twin's.)
* ``I``: types, ``NOT_FOUND`` / ``IN_USE`` (a name another open connection owns);
  input recipe ids are 1, 2, 3, ... per connection in the order asked, whatever their
  outcome, as ur_rtde hard-codes them.
* Recipe ids are one byte: a connection has at most 255 output and 255 input recipes;
  one more is refused (recipe id 0; inputs all ``NOT_FOUND``), with a log line.
* ``S``: refused (0) without a valid output recipe, as the controller does; else 1.
  ``P``: 1. Data packages of each output recipe go out on the controller cycles its
  frequency picks (:class:`~cellcal.mocks.ur.rtde_codec.Decimation`): at 125 Hz every
  4th cycle, the timestamps 8 ms apart exactly.
* ``U`` from the client: applied at once (registers, speed slider, outputs with masks).
"""

from __future__ import annotations

import logging
import struct
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from cellcal.mocks.ur import rtde_codec as rtde
from cellcal.mocks.ur.fields import INPUT_TYPES, OUTPUT_TYPES, Fields

log = logging.getLogger("cellcal.mocks.ur")

CONTROLLER_VERSION = (5, 11, 1, 108318)
#: recipe ids are one byte: the recipes a connection may set up, of each kind
MAX_RECIPES = 255


@dataclass
class OutputRecipe:
    recipe_id: int
    st: struct.Struct
    getters: list[Callable[[], Any]]
    rate: rtde.Decimation


@dataclass
class InputRecipe:
    st: struct.Struct
    fields: list[tuple[str, str]]  # (name, type); empty: a refused recipe


class RtdeSession:
    """The RTDE state of one connection ``cid``; ``owners`` maps input names to the
    connection that owns them (shared by all connections of the controller)."""

    def __init__(self, cid: int, fields: Fields, owners: dict[str, int], host: str) -> None:
        self.cid = cid
        self.fields = fields
        self.owners = owners
        self.host = host
        self.protocol = 1
        self.started = False
        self.outputs: list[OutputRecipe] = []
        self.inputs: dict[int, InputRecipe] = {}

    def close(self) -> None:
        """The connection is gone: free its inputs."""
        for name in [n for n, owner in self.owners.items() if owner == self.cid]:
            del self.owners[name]

    def handle(self, mtype: int, payload: bytes) -> list[bytes]:
        """The frames answering one message of the client."""
        if mtype == rtde.REQUEST_PROTOCOL_VERSION:
            version = struct.unpack(">H", payload[:2])[0] if len(payload) >= 2 else 0
            ok = version in (1, 2)
            if ok:
                self.protocol = version
            return [rtde.frame(mtype, rtde.success(ok))]
        if mtype == rtde.GET_URCONTROL_VERSION:
            return [rtde.frame(mtype, struct.pack(">IIII", *CONTROLLER_VERSION))]
        if mtype == rtde.SETUP_OUTPUTS:
            return self._setup_outputs(payload)
        if mtype == rtde.SETUP_INPUTS:
            return [rtde.frame(mtype, self._setup_inputs(payload))]
        if mtype == rtde.START:
            ok = bool(self.outputs)
            if ok:
                self.started = True
                for r in self.outputs:
                    r.rate.restart()
            return [rtde.frame(mtype, rtde.success(ok))]
        if mtype == rtde.PAUSE:
            self.started = False
            return [rtde.frame(mtype, rtde.success(True))]
        if mtype == rtde.DATA_PACKAGE:
            self._data_from_client(payload)
        elif mtype != rtde.TEXT_MESSAGE:
            log.warning("UR twin %s: unknown RTDE message type %d", self.host, mtype)
        return []

    def cycle(self) -> list[bytes]:
        """The data packages due on this controller cycle."""
        if not self.started:
            return []
        out = []
        for r in self.outputs:
            if r.rate.due():
                values = [g() for g in r.getters]
                body = rtde.data_package(self.protocol, r.recipe_id, r.st, values)
                out.append(rtde.frame(rtde.DATA_PACKAGE, body))
        return out

    # -- setup ------------------------------------------------------------------------

    def _setup_outputs(self, payload: bytes) -> list[bytes]:
        frequency, names = rtde.parse_output_setup(self.protocol, payload)
        if frequency is not None and not rtde.valid_frequency(frequency):
            log.info("UR twin %s: output frequency %r refused", self.host, frequency)
            text = f"Invalid output frequency {frequency:g} Hz: must be within (0, 500]"
            reply = rtde.setup_outputs_reply(self.protocol, 0, [])
            return [
                rtde.frame(rtde.TEXT_MESSAGE, rtde.text_message(self.protocol, text)),
                rtde.frame(rtde.SETUP_OUTPUTS, reply),
            ]
        types: list[str] = []
        getters: list[Callable[[], Any]] = []
        for name in names:
            getter = self.fields.getter(name)
            if getter is None:
                types.append("NOT_FOUND")
                log.info("UR twin %s: output %r NOT_FOUND", self.host, name)
            else:
                types.append(OUTPUT_TYPES[name])
                getters.append(getter)
        rid = 0
        fits = names and "NOT_FOUND" not in types
        if fits and self.protocol >= 2 and len(self.outputs) >= MAX_RECIPES:
            log.warning(
                "UR twin %s: connection %d asks for a %dth output recipe: refused",
                self.host,
                self.cid,
                MAX_RECIPES + 1,
            )
            return [rtde.frame(rtde.SETUP_OUTPUTS, rtde.setup_outputs_reply(2, 0, types))]
        if fits:
            if self.protocol < 2:
                self.outputs.clear()
            rid = len(self.outputs) + 1
            rate = rtde.Decimation(rtde.MAX_FREQUENCY if frequency is None else frequency)
            self.outputs.append(OutputRecipe(rid, rtde.data_struct(types), getters, rate))
        log.debug("UR twin %s: output recipe %d at %s Hz: %s", self.host, rid, frequency, names)
        return [rtde.frame(rtde.SETUP_OUTPUTS, rtde.setup_outputs_reply(self.protocol, rid, types))]

    def _setup_inputs(self, payload: bytes) -> bytes:
        names = rtde.parse_names(payload)
        if len(self.inputs) >= MAX_RECIPES:
            log.warning(
                "UR twin %s: connection %d asks for a %dth input recipe: refused",
                self.host,
                self.cid,
                MAX_RECIPES + 1,
            )
            return rtde.setup_inputs_reply(0, ["NOT_FOUND"] * len(names))
        types: list[str] = []
        for name in names:
            owner = self.owners.get(name)
            if name not in INPUT_TYPES:
                types.append("NOT_FOUND")
                log.info("UR twin %s: input %r NOT_FOUND", self.host, name)
            elif owner is not None and owner != self.cid:
                types.append("IN_USE")
            else:
                types.append(INPUT_TYPES[name])
        rid = len(self.inputs) + 1
        if names and all(t in rtde.TYPE_CODES for t in types):
            for name in names:
                self.owners[name] = self.cid
            self.inputs[rid] = InputRecipe(
                rtde.data_struct(types), list(zip(names, types, strict=True))
            )
        else:
            self.inputs[rid] = InputRecipe(struct.Struct(">"), [])
        log.debug("UR twin %s: input recipe %d: %s -> %s", self.host, rid, names, types)
        return rtde.setup_inputs_reply(rid, types)

    def _data_from_client(self, payload: bytes) -> None:
        if not payload:
            return
        rid = payload[0]
        recipe = self.inputs.get(rid)
        if recipe is None or not recipe.fields:
            log.warning("UR twin %s: data for unknown input recipe %d", self.host, rid)
            return
        if len(payload) - 1 != recipe.st.size:
            log.warning(
                "UR twin %s: input recipe %d: %d bytes, expected %d",
                self.host,
                rid,
                len(payload) - 1,
                recipe.st.size,
            )
            return
        flat = list(recipe.st.unpack_from(payload, 1))
        values: dict[str, Any] = {}
        for name, typ in recipe.fields:
            n = rtde.value_count(typ)
            chunk, flat = flat[:n], flat[n:]
            values[name] = chunk if n > 1 else chunk[0]
        self.fields.set_inputs(values)
