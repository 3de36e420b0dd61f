import sys

from services.robot_io.service import RobotIoService
from shared.runner import run

sys.exit(run(RobotIoService))
