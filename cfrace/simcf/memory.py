"""The memory subsystem of the simulated Crazyflie as the firmware serves it on the CRTP MEM port
(port 4): src/modules/src/crtp_mem.c (memSettingsProcess, memReadProcess, memWriteProcess) over the
handlers that src/modules/src/mem.c registers, and the memories that cflib 0.1.34's
``Crazyflie.mem`` reads on connect (``get_mems(type)``, ``query_all_memories``).

Channels: 0 settings (command 1: the number of memories; command 2 + id: id, type, size uint32, an
8-byte serial of zeros), 1 read (id, address uint32, length -> the same, status 0 and the data, or
EIO without data), 2 write (id, address uint32, data -> id, address, status 0 or EIO). A read or
write that does not fit inside the memory fails with EIO, as the firmware's handlers do.

Memories, in the firmware's registration order (restricted to the emulated ones):

* trajectory memory (MEM_TYPE_TRAJ 0x12, 4096 bytes; crtp_commander_high_level.c
  handleMemRead/handleMemWrite): the high-level commander's (simcf/planner.py);
* memory tester (MEM_TYPE_TESTER 0x15, 4096 bytes; mem.c handleMemTesterRead/Write): reads give
  each address's low byte, writes always succeed;
* deck memory (MEM_TYPE_DECK_MEM 0x19; src/deck/core/deck_memory.c): version 3, then per deck two
  32-byte infos (primary, secondary): bit field, required hash and length, base address, name. Of
  the simulated decks only the Lighthouse deck has a deck memory (its FPGA flash: reported valid and
  started, neither readable nor writable here); the command section (0x1000) accepts writes;
* with the LED ring deck (``ledring``; src/deck/drivers/src/ledring12.c): the LED colours
  (MEM_TYPE_LED12 0x10, 12 LEDs x RGB565) and the LED timings (MEM_TYPE_LEDMEM 0x17, 10 x 4 bytes;
  its size is reported with the 4-byte hash in front, as the firmware does).

Not emulated: the EEPROM (MEM_TYPE_EEPROM), the decks' 1-wire memories (MEM_TYPE_OW), the
Lighthouse base station memory (MEM_TYPE_LH); so the ids differ from a real drone's: look memories
up by type, as cflib's examples do.
"""

from __future__ import annotations

import errno
import struct
import weakref
from dataclasses import dataclass
from typing import Callable

from cfrace.simcf.planner import Planner

TYPE_LED12, TYPE_TRAJ, TYPE_TESTER, TYPE_LEDMEM, TYPE_DECK_MEM = 0x10, 0x12, 0x15, 0x17, 0x19
CMD_GET_NBR, CMD_GET_INFO = 1, 2
SERIAL_LENGTH = 8             #: the serial (zeros) is padded to 8 bytes for old clients (crtp_mem.c)
MAX_READ = 24                 #: bytes of data in one read answer (30 - id, address, status)
TESTER_SIZE = 0x1000
LEDRING_LEDS = 12             #: CONFIG_DECK_LEDRING_NBR_LEDS default
LEDRING_TIMINGS = 10 * 4      #: LEDRING_TIME_MEM_SIZE timings of 4 bytes
DECK_MEM_SECTION = 0x10000000  #: bytes per deck memory section (deck_memory.c DECK_MEM_MAX_SIZE)
DECK_MAX_COUNT = 4
DECK_INFO_SIZE = 0x20
DECK_INFO_VERSION = 3
DECK_COMMAND_BASE = 0x1000
DECK_VALID, DECK_STARTED = 1, 2

#: the deck drivers' names (deck.c DeckDriver.name) of the simulated decks
DECK_NAMES = {"lighthouse": "bcLighthouse4", "flow": "bcFlow2", "ledring": "bcLedRing"}
#: decks whose driver has a deck memory, with the bit field the simulator reports for it
DECK_MEMORY_BITS = {"lighthouse": DECK_VALID | DECK_STARTED}


@dataclass
class Memory:
    """One registered memory handler (mem.h MemoryHandlerDef_t)."""

    type: int
    size: int                                         #: bytes, as reported in the info answer
    read: Callable[[int, int], bytes | None]          #: (address, length) -> data, None = failed
    write: Callable[[int, bytes], bool] | None        #: (address, data) -> ok; None: not writable


def _ram(buffer: bytearray, size: int | None = None) -> tuple[Callable, Callable]:
    """Read and write of a RAM buffer with the firmware's bounds check (address + length <= size)."""
    limit = len(buffer) if size is None else size

    def read(addr: int, n: int):
        return bytes(buffer[addr:addr + n]) if addr + n <= limit else None

    def write(addr: int, data: bytes) -> bool:
        if addr + len(data) > limit:
            return False
        buffer[addr:addr + len(data)] = data
        return True
    return read, write


def _deck_info(decks: tuple[str, ...]) -> bytes:
    """The deck memory's info section: version, then two infos per deck (deck_memory.c
    populateDeckMemoryInfos), zeros for decks without a deck memory."""
    out = bytearray([DECK_INFO_VERSION])
    for k, deck in enumerate(decks):
        info = bytearray(2 * DECK_INFO_SIZE)
        bits = DECK_MEMORY_BITS.get(deck)
        if bits:
            name = DECK_NAMES[deck].encode()[:17]
            struct.pack_into("<BBIII", info, 0, bits, 0, 0, 0, (2 * k + 1) * DECK_MEM_SECTION)
            info[0x0E:0x0E + len(name)] = name
        out += info
    return bytes(out)


def _deck_memory(decks: tuple[str, ...]) -> Memory:
    info = _deck_info(decks)

    def read(addr: int, n: int):
        if addr < DECK_MEM_SECTION:                          # info section: zeros past the decks
            return (info[addr:addr + n] if addr < len(info) else b"").ljust(n, b"\0")
        return None                                          # a deck's own memory: not readable here

    def write(addr: int, data: bytes) -> bool:
        return addr < DECK_MEM_SECTION                       # the command section takes anything

    return Memory(TYPE_DECK_MEM, DECK_MEM_SECTION * (DECK_MAX_COUNT + 1), read, write)


def _tester() -> Memory:
    return Memory(TYPE_TESTER, TESTER_SIZE, lambda addr, n: bytes((addr + k) & 0xFF for k in range(n)),
                  lambda addr, data: True)


def build_memories(planner: Planner, decks: tuple[str, ...]) -> list[Memory]:
    """The memories of one drone, in registration order (index = memory id)."""
    mems = [Memory(TYPE_TRAJ, len(planner.memory), *_ram(planner.memory)), _tester(), _deck_memory(decks)]
    if "ledring" in decks:
        mems.append(Memory(TYPE_LED12, 2 * LEDRING_LEDS, *_ram(bytearray(2 * LEDRING_LEDS))))
        mems.append(Memory(TYPE_LEDMEM, 4 + LEDRING_TIMINGS, *_ram(bytearray(LEDRING_TIMINGS))))
    return mems


_BY_PLANNER: "weakref.WeakKeyDictionary[Planner, list[Memory]]" = weakref.WeakKeyDictionary()


def memories_of(planner: Planner, decks: tuple[str, ...]) -> list[Memory]:
    """The memories of the drone whose high-level commander is ``planner`` (a reboot makes a new
    planner, so its RAM memories start empty again, as the firmware's)."""
    mems = _BY_PLANNER.get(planner)
    if mems is None:
        mems = _BY_PLANNER[planner] = build_memories(planner, tuple(decks))
    return mems


def handle(mems: list[Memory], channel: int, payload: bytes) -> tuple[list[tuple[int, bytes]], str | None]:
    """One MEM packet -> ([(channel, answer payload)], console line or None)."""
    if channel == 0 and payload:
        if payload[0] == CMD_GET_NBR:
            return [(0, bytes([CMD_GET_NBR, len(mems)]))], None
        if payload[0] == CMD_GET_INFO and len(payload) >= 2:
            ident = payload[1]
            if ident >= len(mems):
                return [(0, bytes([CMD_GET_INFO, ident]))], f"MEM: no memory {ident} (the firmware asserts)"
            m = mems[ident]
            return [(0, struct.pack("<BBBI", CMD_GET_INFO, ident, m.type, m.size) + bytes(SERIAL_LENGTH))], None
        return [], None
    if channel == 1:
        if len(payload) < 6:
            return [], f"MEM: a read request of {len(payload)} bytes (needs 6: id, address, length), dropped"
        ident, addr, n = struct.unpack_from("<BIB", payload, 0)
        head = payload[:5]
        if ident >= len(mems):
            return [(1, head + bytes([errno.EIO]))], f"MEM: no memory {ident} (the firmware asserts), EIO"
        if n > MAX_READ:
            return [(1, head + bytes([errno.EIO]))], f"MEM: a read of {n} bytes (at most {MAX_READ}), EIO"
        data = mems[ident].read(addr, n)
        if data is None:
            return [(1, head + bytes([errno.EIO]))], None
        return [(1, head + b"\0" + data)], None
    if channel == 2:
        if len(payload) < 5:
            return [], f"MEM: a write request of {len(payload)} bytes (needs 5 + data: id, address), dropped"
        ident = payload[0]
        head = payload[:5]
        if ident >= len(mems):
            return [(2, head + bytes([errno.EIO]))], f"MEM: no memory {ident} (the firmware asserts), EIO"
        m = mems[ident]
        ok = m.write is not None and m.write(struct.unpack_from("<I", payload, 1)[0], bytes(payload[5:]))
        return [(2, head + (b"\0" if ok else bytes([errno.EIO])))], None
    return [], None
