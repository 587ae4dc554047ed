"""The command line's appliance commands: `xrf serve` and `xrf login`."""
