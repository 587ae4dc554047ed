"""Who may do what: accounts, sessions and permissions, the bench lease, ownership, the audit log, body limits."""
