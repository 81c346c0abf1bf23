"""The wire: protocol messages, their codec, ZeroMQ transport and CURVE security."""
