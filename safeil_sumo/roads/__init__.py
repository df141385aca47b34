"""Roads: generated test tracks, SUMO nets and routes read into lanes, the n74 motorway, roads
rebuilt from recordings."""
