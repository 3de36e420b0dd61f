"""Pure libraries the services and tools stand on: each imports only ``shared/`` (and third-party
packages), never a service, ``bench``, ``evaluation``, ``deploy`` or ``tools``
(``tests/unit/test_architecture.py`` enforces it).

- ``pointrender``: point-cloud rendering (the renderer's splats, occlusion, level of detail);
- ``world``: simulated worlds (scene files, generated houses, navigation grid, episodes);
- ``ros2``: the ROS 2 protocol over zenoh (CDR messages, key styles, nodes, robot profiles).
"""
