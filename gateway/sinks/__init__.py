"""Where samples go: the console now; MQTT and Prometheus with the publishing release."""
