"""XRF Lab host side: channels to the loop, the .msg toolchain, builds, the appliance and the CLI."""
