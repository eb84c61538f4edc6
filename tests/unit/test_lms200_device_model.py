"""The emulated LMS200's answers, request by request (no pty, no clock)."""

from __future__ import annotations

import numpy as np
import pytest

from lrfslam.drivers.lms200 import protocol as p
from lrfslam.drivers.lms200.device_model import (
    TYPE_STRING,
    EmulatedLms200,
    SimScanSource,
    scan_period_s,
)


def request(telegram: bytes) -> p.Telegram:
    return p.TelegramParser(replies=False).feed(telegram)[0]


def reply(raw: bytes) -> p.Telegram:
    return p.TelegramParser().feed(raw)[0]


def only_reply(device: EmulatedLms200, telegram: bytes) -> p.Telegram:
    reaction = device.handle(request(telegram))
    assert len(reaction.replies) == 1
    return reply(reaction.replies[0])


def test_power_on_telegram_is_the_published_one():
    assert EmulatedLms200().power_on_telegram() == bytes.fromhex(
        "02 80 17 00 90" + TYPE_STRING.hex() + "10 63 5E")


def test_baud_change_is_acknowledged_then_applied():
    device = EmulatedLms200()
    reaction = device.handle(request(p.baud_request(38400)))
    assert reaction.replies == (bytes.fromhex("02 80 03 00 A0 00 10 16 0A"),)
    assert reaction.new_baud == 38400 and device.baud == 9600  # the emulator switches after sending


def test_variant_accept_and_reject():
    device = EmulatedLms200()
    ok = only_reply(device, p.variant_request(p.VARIANT_180_1))
    assert p.is_accepted(ok) and p.variant_of(ok) == p.VARIANT_180_1 == device.variant
    bad = only_reply(device, p.build_request(bytes.fromhex("3B B4 00 19 00")))  # 180°/0.25° does not exist
    assert not p.is_accepted(bad) and p.variant_of(bad) == p.VARIANT_180_1


def test_config_write_needs_installation_mode():
    device = EmulatedLms200(units=p.Units.CM)
    assert p.config_of(only_reply(device, p.REQUEST_CONFIG))[p.CONFIG_UNITS] == p.Units.CM
    mm = p.config_with(device.config, units=p.Units.MM, measuring_mode=0)
    assert not p.is_accepted(only_reply(device, p.config_write_request(mm)))
    assert not p.is_accepted(only_reply(device, p.installation_request(b"WRONG_PW")))
    assert p.is_accepted(only_reply(device, p.installation_request()))
    assert p.is_accepted(only_reply(device, p.config_write_request(mm)))
    assert device.units is p.Units.MM


def test_streaming_modes_scan_request_and_unknown_commands():
    device = EmulatedLms200()
    assert p.is_accepted(only_reply(device, p.START_CONTINUOUS)) and device.streaming
    assert p.is_accepted(only_reply(device, p.STOP_CONTINUOUS)) and not device.streaming
    assert device.handle(request(p.REQUEST_SCAN)).send_scan
    assert only_reply(device, p.build_request(b"\x10")).command == p.REPLY_REFUSED  # reset: not emulated


def test_scan_telegram_uses_configured_units_and_indices():
    device = EmulatedLms200(units=p.Units.CM)
    device.config = bytes([*device.config[:4], p.AVAILABILITY_INDICES, *device.config[5:]])
    ranges = np.full(361, 2.5)
    ranges[3] = np.inf
    scan = p.parse_scan(reply(device.scan_telegram(ranges, scan_number=300)))
    assert scan.units is p.Units.CM and scan.ranges_m.size == 361
    assert scan.ranges_m[0] == pytest.approx(2.5) and scan.ranges_m[3] == np.inf
    assert (scan.scan_index, scan.telegram_index) == (300 % 256, 0)


def test_power_cycle_keeps_the_eeprom_configuration():
    device = EmulatedLms200(units=p.Units.CM)
    device.handle(request(p.START_CONTINUOUS))
    device.variant = p.VARIANT_180_1
    device.baud = 38400
    device.power_cycle()
    assert (device.baud, device.variant, device.streaming, device.units) == (9600, p.VARIANT_180_05, False, p.Units.CM)


def test_sim_scans_depend_only_on_seed_variant_and_number():
    a, b = SimScanSource(seed=5), SimScanSource(seed=5)
    np.testing.assert_array_equal(a(p.VARIANT_180_1, 40), b(p.VARIANT_180_1, 40))
    assert not np.array_equal(a(p.VARIANT_180_1, 40), a(p.VARIANT_180_1, 41), equal_nan=True)
    assert a(p.VARIANT_100_025, 3).shape == (401,)
    assert scan_period_s(p.VARIANT_100_025) == pytest.approx(4 * scan_period_s(p.VARIANT_180_1))
