import signal
import sys

import uvicorn

from services.gateway.app import create_app
from services.gateway.settings import GatewaySettings
from shared.logs import configure_logging
from shared.runner import freeze_started_heap


def main() -> int:
    settings = GatewaySettings(_cli_parse_args=True)
    configure_logging("gateway", settings.instance, settings.log_level, settings.log_json)
    # uvicorn re-raises the signal that stopped it once it has shut down gracefully; a no-op
    # handler underneath makes that a clean exit (status 0) instead of death by SIGTERM.
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: None)
    app = create_app(settings)
    freeze_started_heap()  # its imports: fastapi, pydantic, the routes (what the lifespan opens stays collectable)
    uvicorn.run(app, host=settings.host, port=settings.port, log_config=None,
                log_level=settings.log_level.lower(),
                # SSE streams never end by themselves; give them a grace period, then close them.
                timeout_graceful_shutdown=settings.shutdown_grace_s or None)
    return 0


sys.exit(main())
