// XenoFileHandler — names the log file: <name>_YYMMDD_HHMMSS.<type> when add_timestamp. Under the
// appliance ($XRF_LOG_DIR = the run folder) every name, absolute ones included, is mapped into the
// run folder with the same layout ("/home/x/logs/log" -> "<run>/home/x/logs/log", ".." never above
// it) and the mapping is printed at construction. Parent folders are created and the file is
// appended to; the loop process's helper thread (or the appliance) opens and writes it, never the
// loop thread. When this process writes it, the constructor tries it at once and prints why not.
#pragma once

// XRF2's XenoFileHandler.hpp included these (std::filesystem, stat, ...); student code relies on them.
#include <cstdio>
#include <error.h>
#include <filesystem>
#include <stdint.h>
#include <string>
#include <sys/stat.h>
#include <sys/types.h>
#include <time.h>
#include <unistd.h>

#include "ICommunication.h"
#include "debug_settings.h"
#include "xrf_evl_compat.h"

class XenoFileHandler
{
public:
    XenoFileHandler(bool add_timestamp, const std::string &name, const std::string &type,
                    mode_t mode = 0666);
    const char *path() const { return path_; }
    mode_t mode() const { return mode_; }

private:
    char path_[512];
    mode_t mode_;
};
