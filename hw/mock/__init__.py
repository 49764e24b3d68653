"""The MuJoCo-backed mock Go2: ``hw.mock.robot.MockRobot``, ``hw.mock.config.MockConfig``,
the ``a2i-mock`` command (``hw.mock.cli:main``). Reference: ``docs/mock-robot.md``.

Nothing here is imported eagerly: ``hw.mock.robot`` loads MuJoCo.
"""
