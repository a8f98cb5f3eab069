"""The plant's side of compd: MQTT Sparkplug B telemetry with store and forward, and a read-only OPC UA server."""
