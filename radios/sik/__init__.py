"""SiK telemetry radios: parameter table, radio-side AT interpreter, host-side configurator."""
