"""The one service runner: config layering, the Zenoh bus, replay, lifecycle."""
