"""The lab room (issue 21): one educator page for every bench, one class list, over Eclipse
Mosquitto. docs/educators/room.md is the educators' guide; the modules, one concept each:

- topics.py: the MQTT topics; payloads.py: what each carries (one bounded model each) -- the contract
- broker.py: mosquitto's config, ACL, passwords (mosquitto_passwd) and TLS files (openssl)
- mqtt.py: connecting with paho-mqtt (credentials, TLS, keep-alive, reconnect)
- publisher.py: a bench's status and events (a hub listener: one more observer of the run)
- commands.py: what a bench does with the room's commands (stop, message, self-check)
- accounts_sync.py: the class list, published by the room and applied by every bench
- sso.py: short-lived Ed25519 tokens: the room's click-through to a bench, a bench's own fetches
- enrol.py: join codes, `xrf room join` and the bench's enrolment file (its secrets)
- bench.py: wiring the above into an appliance (enabled once the bench is enrolled)
- service.py: the room service (`xrf room`): its state, API, page and WebSocket
"""
