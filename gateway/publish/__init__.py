"""Where samples go: the shared state, MQTT (with its store), Prometheus and the console."""
