"""The live view from outside: a Foxglove client, the layout file, a picture of what a client
receives."""
