"""SICK LMS200 laser scanner over RS-232/RS-422.

protocol (pure: telegrams, CRC, B0 scans; framing in framing) · port (the
pyserial driver, :class:`~lrfslam.drivers.lms200.port.Lms200`) · emulator
(pty stand-in for the device; its protocol behaviour in device_model).
"""
