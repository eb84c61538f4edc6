"""Messages: the only package that knows the wire format.

``types`` holds the in-memory messages (frozen dataclasses with numpy arrays),
``codec`` converts them to and from the versioned protobuf schemas generated
from ``schemas/``, and ``topics`` is the one registry of key expressions.
"""
