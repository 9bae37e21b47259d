"""The Zenoh service around one World: configuration, the server and its parts."""
