import sys

from services.renderer.service import RendererService
from shared.runner import run

sys.exit(run(RendererService))
