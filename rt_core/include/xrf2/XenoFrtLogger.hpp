// XenoFrtLogger — logs a packed struct once per cycle into the lossless log ring. The file is
// written in-band (see XenoFileHandler). initialise() is idempotent.
#pragma once

#include <cassert>
#include <cstdint>
#include <string.h>
#include <string>

#include "XenoFileHandler.hpp"
#include "debug_settings.h"
#include "xrf/logformat.h"

#ifndef MSEC
#define MSEC 1000000L
#endif
#ifndef SEC
#define SEC 1000000000L
#endif

// XRF2's spelling and the course guide's; both name the codes of the log file format.
enum VariableTypes {
    boolean = XRF_LOG_BOOL,
    character = XRF_LOG_CHAR,
    integer = XRF_LOG_INT,
    float_ = XRF_LOG_FLOAT,
    double_ = XRF_LOG_DOUBLE,
    long_int = XRF_LOG_LONG_INT
};
enum VariableTypeIds {
    id_bool = XRF_LOG_BOOL,
    id_char = XRF_LOG_CHAR,
    id_int = XRF_LOG_INT,
    id_float = XRF_LOG_FLOAT,
    id_double = XRF_LOG_DOUBLE,
    id_long_int = XRF_LOG_LONG_INT
};

// XRF2's description of a logged variable and of the whole record (its logger kept one); part of
// the header's surface, so student code naming them compiles.
struct variableInfo {
    const char *name;
    VariableTypes type;
};
struct loggerInfo {
    void *data_ptr;
    int data_size;
    int number_var;
    variableInfo var_info[100];
};

class XenoFrtLogger
{
public:
    static constexpr int max_variables = 100;

    XenoFrtLogger(XenoFileHandler &file, void *data);
    // In the order of the packed struct's fields. Returns 0, or -1 (full, unknown type, or
    // after initialise() with a different set).
    int addVariable(const char *name, int type);
    int addVariable(const std::string &name, int type) { return addVariable(name.c_str(), type); }
    int initialise();
    bool isInitialised() const { return initialised_; }
    int start();
    int stop();
    bool isStarted() const { return started_; }
    // One record; -1 when not started, -2 when the ring was full (the record is counted lost).
    int log();
    uint32_t recordSize() const { return record_size_; }

private:
    bool publish();
    XenoFileHandler &file_;
    const void *data_;
    struct Var {
        char name[64];
        int type;
        int offset;
    } vars_[max_variables];
    int nvars_ = 0;
    uint32_t record_size_ = 0;
    bool initialised_ = false;
    bool published_ = false;
    bool started_ = false;
    uint64_t seq_ = 0;
};
