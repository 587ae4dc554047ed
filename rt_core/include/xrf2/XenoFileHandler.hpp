// XenoFileHandler — names the log file: <name>_YYMMDD_HHMMSS.<type> when add_timestamp, relative
// names under $XRF_LOG_DIR. Parent folders are created and the file is appended to; the loop
// process's helper thread (or the appliance) opens and writes it, never the loop thread.
#pragma once

#include <string>
#include <sys/types.h>

class XenoFileHandler {
public:
    XenoFileHandler(bool add_timestamp, const std::string &name, const std::string &type,
                    mode_t mode = 0666);
    const char *path() const { return path_; }
    mode_t mode() const { return mode_; }

private:
    char path_[512];
    mode_t mode_;
};
