"""The dashboards' live channel: the server's messages (one typed model each) and the hub that fans them out."""
