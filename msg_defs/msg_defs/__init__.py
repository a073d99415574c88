"""msg_defs: inkdiag's wire contract (topics, QoS, layouts, codecs, validation)."""
